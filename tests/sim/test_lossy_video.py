from pathlib import Path

import av
import numpy as np

from perchpose.sim.lossy_video import encode_h264, lose_packets


def _images(count: int) -> list[np.ndarray]:
    return [np.full((48, 64, 3), 20 * k, np.uint8) for k in range(count)]


def test_a_key_frame_every_gop_frames_and_no_b_frames(tmp_path: Path) -> None:
    video = encode_h264(_images(12), tmp_path / "v.mp4", gop=4)
    with av.open(str(video)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264"
        packets = [p for p in container.demux(stream) if p.size > 0]
    assert [p.is_keyframe for p in packets] == [k % 4 == 0 for k in range(12)]
    assert [p.pts for p in packets] == sorted(p.pts for p in packets)  # sent in display order


def test_lost_and_cut_packets(tmp_path: Path) -> None:
    clean = encode_h264(_images(12), tmp_path / "v.mp4", gop=4)
    lossy = lose_packets(clean, tmp_path / "l.mp4", drop={5}, zero_half={9})
    with av.open(str(clean)) as a, av.open(str(lossy)) as b:
        sent = [bytes(p) for p in a.demux(a.streams.video[0]) if p.size > 0]
        kept = [bytes(p) for p in b.demux(b.streams.video[0]) if p.size > 0]
    assert kept[:5] == sent[:5]
    assert kept[5:8] == sent[6:9]
    half = len(sent[9]) // 2
    assert kept[8][:half] == sent[9][:half]
    assert kept[8][half:] == bytes(len(sent[9]) - half)
    assert kept[9:] == sent[10:]
