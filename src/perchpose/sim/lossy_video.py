"""Rendered frames as a camera's H.264 encoder sends them, and as a lossy link delivers them
(PyAV's libx264): to try a pipeline on the frames a lost packet spoils, with the truth known.

``encode_h264`` writes images as an MP4 (or MPEG-TS, by the name's suffix) with a key frame
every ``gop`` frames and no B-frames, as low-latency camera encoders are set; ``lose_packets``
copies it packet by packet, leaving out the packets of some frames and zeroing the second half
of others."""

from __future__ import annotations

from collections.abc import Iterable
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import numpy as np
from numpy.typing import NDArray


def encode_h264(
    images: Iterable[NDArray[np.uint8]],
    path: Path,
    gop: int,
    fps: int = 30,
    crf: int = 18,
    times_ms: list[int] | None = None,
    intra_refresh: bool = False,
) -> Path:
    """``images`` (BGR, all one size) as H.264 at ``fps`` (or stamped ``times_ms``): libx264,
    a key frame every ``gop`` frames, no B-frames, constant quality ``crf``. With
    ``intra_refresh``, as low-latency links send it: a key frame only first, then a column of
    intra blocks sweeping the picture every ``gop`` frames, each sweep's start marked as a
    recovery point."""
    out = av.open(str(path), "w")
    stream = out.add_stream("libx264", rate=fps)
    stream.pix_fmt = "yuv420p"
    stream.options = {
        "g": str(gop),
        "keyint_min": str(gop),
        "bf": "0",
        "sc_threshold": "0",
        "crf": str(crf),
    }
    if intra_refresh:
        stream.options["x264-params"] = "intra-refresh=1"
    if times_ms is not None:
        stream.codec_context.time_base = Fraction(1, 1000)
    for k, image in enumerate(images):
        if k == 0:
            stream.height, stream.width = image.shape[:2]
        frame = av.VideoFrame.from_ndarray(image, format="bgr24")
        if times_ms is not None:
            frame.pts, frame.time_base = times_ms[k], Fraction(1, 1000)
        for packet in stream.encode(frame):
            out.mux(packet)
    for packet in stream.encode():
        out.mux(packet)
    out.close()
    return path


def lose_packets(clean: Path, damaged: Path, drop: set[int], zero_half: set[int]) -> Path:
    """``clean`` copied packet by packet to ``damaged`` without the packets of the frames in
    ``drop`` and with the second half of those in ``zero_half`` zeroed (frames counted from 0 in
    the order they were sent: there are no B-frames)."""
    source = av.open(str(clean))
    video = source.streams.video[0]
    out = av.open(str(damaged), "w")
    stream = out.add_stream_from_template(video)
    packets = (p for p in source.demux(video) if p.size > 0)
    for index, packet in enumerate(packets):
        if index in drop:
            continue
        sent: av.Packet[Any] = packet
        if index in zero_half:
            data = bytearray(bytes(packet))
            half = len(data) // 2
            data[half:] = bytes(len(data) - half)
            sent = av.Packet(bytes(data))
            sent.pts, sent.dts, sent.time_base = packet.pts, packet.dts, packet.time_base
        sent.stream = stream
        out.mux(sent)
    out.close()
    source.close()
    return damaged
