from perchpose.io.ros.transport import BEST_EFFORT, RELIABLE, StampGaps, matching_reliability


def test_the_subscription_matches_its_publishers_as_ros2_topic_echo_does() -> None:
    assert matching_reliability([]) is None  # nothing to match yet
    assert matching_reliability([RELIABLE]) == RELIABLE
    assert matching_reliability([RELIABLE, RELIABLE]) == RELIABLE
    # a reliable subscription would not hear a best-effort publisher at all
    assert matching_reliability([RELIABLE, BEST_EFFORT]) == BEST_EFFORT


def test_gaps_in_the_stamps_count_the_frames_lost_in_them() -> None:
    gaps = StampGaps()
    period = 100_000_000  # 10 Hz
    stamps = [k * period for k in range(8)]
    stamps += [10 * period, 11 * period]  # 8 and 9 lost
    stamps += [11 * period + 130_000_000]  # late by 30 ms: jitter, not a loss
    stamps += [15 * period]  # 2 lost (13 and 14 by the period)
    lost = [gaps.seen(t) for t in stamps]
    assert lost == [0] * 8 + [2, 0, 0, 2]
    assert gaps.lost == 4
    # a camera that starts over: no loss counted across the jump back, nor until its period
    # is known again
    assert gaps.seen(0) == 0
    assert gaps.seen(5 * period) == 0
    assert gaps.lost == 4
