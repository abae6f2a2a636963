from pathlib import Path

import numpy as np
import pytest

from perchpose.io.decoding import AvCapture, ReferenceChain
from perchpose.io.sources import open_source
from perchpose.sim.lossy_video import encode_h264, lose_packets

W, H = 160, 120


def test_a_frame_with_errors_damages_the_frames_after_it_until_a_whole_key_frame() -> None:
    chain = ReferenceChain()
    assert chain.frame(0, key=True, corrupt=False) == ""
    assert chain.frame(1, key=False, corrupt=False) == ""
    assert "frame 2 decoded with errors" in chain.frame(2, key=False, corrupt=True)
    assert "since frame 2" in chain.frame(3, key=False, corrupt=False)
    assert chain.broken
    # a key frame that itself decoded with errors mends nothing
    assert "decoded with errors" in chain.frame(4, key=True, corrupt=True)
    assert "since frame 2" in chain.frame(5, key=False, corrupt=False)
    assert chain.frame(6, key=True, corrupt=False) == ""
    assert chain.frame(7, key=False, corrupt=False) == ""
    assert not chain.broken


def test_a_missing_frame_damages_what_is_predicted_after_it() -> None:
    chain = ReferenceChain()
    chain.frame(0, key=True, corrupt=False)
    assert "since frame 1" in chain.frame(3, key=False, corrupt=False, missing_before=2)
    # the chain stays broken from the first missing frame, whatever goes missing after it
    assert "since frame 1" in chain.frame(5, key=False, corrupt=False, missing_before=1)
    # a key frame after a gap needs nothing before it
    assert chain.frame(8, key=True, corrupt=False, missing_before=2) == ""


def test_a_packet_the_demuxer_marked_corrupt() -> None:
    chain = ReferenceChain()
    chain.frame(0, key=True, corrupt=False)
    chain.packet_damaged(2)
    assert chain.frame(1, key=False, corrupt=False) == ""
    assert "frame 2 decoded with errors" in chain.frame(2, key=False, corrupt=False)
    # the lost data may have held the start of the next frame: a key frame there mends nothing
    assert "may hold its rest" in chain.frame(3, key=True, corrupt=False)
    assert "since frame 2" in chain.frame(4, key=False, corrupt=False)
    assert chain.frame(10, key=True, corrupt=False) == ""
    # its frame never came out of the decoder: the next frame may be its rest, and what
    # follows rests on a missing frame
    chain.packet_damaged(12)
    assert "data lost at frame 12" in chain.frame(13, key=True, corrupt=False)
    assert "since frame 12" in chain.frame(14, key=False, corrupt=False)
    assert chain.frame(20, key=True, corrupt=False) == ""


def test_intra_refresh_mends_a_whole_cycle_after_the_damage() -> None:
    """No key frame after the first; access points (recovery points) every 10 frames: the
    picture is whole again at the second access point after the damage, not the first."""
    chain = ReferenceChain()
    chain.frame(0, key=True, corrupt=False)
    assert chain.frame(10, key=False, corrupt=False, access_point=True) == ""
    assert "since frame 13" in chain.frame(14, key=False, corrupt=False, missing_before=1)
    assert "since frame 13" in chain.frame(20, key=False, corrupt=False, access_point=True)
    assert "since frame 13" in chain.frame(29, key=False, corrupt=False)
    assert chain.frame(30, key=False, corrupt=False, access_point=True) == ""
    # new damage inside a cycle starts the count again
    assert "frame 33 decoded with errors" in chain.frame(33, key=False, corrupt=True)
    assert "since frame 33" in chain.frame(40, key=False, corrupt=False, access_point=True)
    assert "decoded with errors" in chain.frame(45, key=False, corrupt=True)
    assert "since frame 33" in chain.frame(50, key=False, corrupt=False, access_point=True)
    assert chain.frame(60, key=False, corrupt=False, access_point=True) == ""


def test_an_intra_refresh_stream_after_a_lost_packet(tmp_path: Path) -> None:
    """libx264's intra refresh (one key frame, then a refresh sweep every 10 frames, each
    start a recovery point): frame 13 lost spoils 14-27 in the pixels; 14-29 are flagged (to
    the second recovery point), and from 30 on every frame is the clean decode again."""
    clean = encode_h264(_moving_square(40), tmp_path / "clean.mp4", gop=10, intra_refresh=True)
    lossy = lose_packets(clean, tmp_path / "lossy.mp4", drop={13}, zero_half=set())
    sent = {f.index: f.image for f in open_source(str(clean))}
    frames = [f for f in open_source(str(lossy)) if f.image is not None]
    assert [f.index for f in frames if f.damaged] == list(range(14, 30))
    for f in frames:
        assert f.image is not None
        difference = np.abs(f.image.astype(int) - sent[f.index].astype(int)).max()
        assert f.damaged or difference == 0, f.index


def _moving_square(frames: int) -> list[np.ndarray]:
    """A bright square moving 2 px a frame over a gradient."""
    images = []
    for k in range(frames):
        image = np.zeros((H, W, 3), np.uint8)
        image[:, :, 1] = np.linspace(0, 200, W, dtype=np.uint8)[None, :]
        image[40:80, 10 + 2 * k : 50 + 2 * k] = 255
        images.append(image)
    return images


@pytest.fixture(scope="module")
def videos(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """clean.mp4 (a key frame every 10 frames) and lossy.mp4: frame 13's packet lost whole,
    frame 25's cut in half."""
    folder = tmp_path_factory.mktemp("h264")
    encode_h264(_moving_square(40), folder / "clean.mp4", gop=10)
    lose_packets(folder / "clean.mp4", folder / "lossy.mp4", drop={13}, zero_half={25})
    return folder


def test_a_clean_stream_has_no_damaged_frame(videos: Path) -> None:
    source = open_source(str(videos / "clean.mp4"))
    frames = list(source)
    assert [f.index for f in frames] == list(range(40))
    assert not any(f.damaged or f.error for f in frames)
    assert source.damaged == source.lost == 0


def test_frames_after_a_lost_packet_are_damaged_until_the_next_key_frame(videos: Path) -> None:
    """Frame 13's packet lost whole and frame 25's cut in half: FFmpeg decodes frames 14-19
    and 26-29 without complaint, from the wrong references; each is flagged, and the key frames
    20 and 30 mend the stream."""
    source = open_source(str(videos / "lossy.mp4"))
    frames = {f.index: f for f in source}
    assert sorted(frames) == list(range(40))
    assert frames[13].image is None
    assert "cannot be decoded" in frames[13].error
    damaged = sorted(i for i, f in frames.items() if f.damaged)
    # frame 25 decodes with errors or not at all, depending on where the cut falls
    assert set(damaged) - {25} == {*range(14, 20), *range(26, 30)}
    for i in damaged:
        assert frames[i].image is not None
        assert "not measured" in frames[i].error
        assert frames[i].file == f"{videos / 'lossy.mp4'}#{i}"
    assert source.damaged == len(damaged)
    # the damage is real: every flagged frame differs from the clean decode (the first after
    # each loss by the square's whole contrast), every other one is the clean decode exactly
    clean = {f.index: f.image for f in open_source(str(videos / "clean.mp4"))}
    for i, f in frames.items():
        if f.image is None:
            continue
        assert clean[i] is not None
        difference = np.abs(f.image.astype(int) - clean[i].astype(int)).max()
        assert (difference > 0) == f.damaged, i
        if i in (14, 26):
            assert difference > 200


@pytest.mark.parametrize("kind", ["jitter", "heavy jitter", "drift"])
def test_a_camera_whose_frame_times_wander_is_not_taken_for_a_lossy_one(
    tmp_path: Path, kind: str
) -> None:
    """Frame times that jitter (33 ms apart give or take 6 ms, software stamps; or 7 ms, a
    fifth of a frame) or drift (the interval growing from 33 to 50 ms, a camera slowing in
    low light): no frame is missing and none flagged; a packet lost from the same stream is
    still found (with 6 ms of jitter: with 7 and more, a gap of two intervals can shrink to
    the 1.5 intervals that say a frame is missing)."""
    if kind.endswith("jitter"):
        rng = np.random.default_rng(4)
        jitter_ms = 6 if kind == "jitter" else 7
        times_ms = [
            round(1000 * k / 30 + 10 + rng.uniform(-jitter_ms, jitter_ms)) for k in range(40)
        ]
    else:
        times_ms = np.cumsum([0] + [round(33.3 + 16.7 * k / 39) for k in range(39)]).tolist()
    video = encode_h264(_moving_square(40), tmp_path / "camera.mp4", gop=40, times_ms=times_ms)
    assert not any(f.damaged for f in open_source(str(video)))
    if kind == "heavy jitter":
        return
    lossy = lose_packets(video, tmp_path / "lossy.mp4", drop={20}, zero_half=set())
    # the 20 frames before the loss are whole, the 19 after it (no key frame follows) damaged
    decoded = [f for f in open_source(str(lossy)) if f.image is not None]
    assert [f.damaged for f in decoded] == [False] * 20 + [True] * 19


def test_a_capture_that_cannot_be_opened(tmp_path: Path) -> None:
    (tmp_path / "text.mp4").write_text("not a video")
    assert AvCapture.open(str(tmp_path / "text.mp4"), live=False) is None
    assert AvCapture.open(str(tmp_path / "absent.mp4"), live=False) is None
