import pytest

from perchpose.io.mavlink.timesync import TimeSync


class Clocks:
    """Our clock and the autopilot's, 1000 s apart; messages take ``delay_ns`` each way."""

    def __init__(self) -> None:
        self.ours_ns = 5_000_000_000
        self.offset_ns = 1_000_000_000_000

    def ours(self) -> int:
        return self.ours_ns

    def round_trip(self, sync: TimeSync, out_ns: int, back_ns: int) -> None:
        tc1, ts1 = sync.request()
        assert tc1 == 0
        self.ours_ns += out_ns
        theirs = self.ours_ns + self.offset_ns  # the autopilot answers with its time
        self.ours_ns += back_ns
        assert sync.handle(theirs, ts1) is None


def test_the_offset_comes_from_the_fastest_round_trip() -> None:
    clocks = Clocks()
    sync = TimeSync(clock_ns=clocks.ours)
    assert sync.offset_ns is None
    assert sync.remote_usec(1.0) is None
    clocks.round_trip(sync, 3_000_000, 9_000_000)  # a slow, lopsided trip: 3 ms off
    assert sync.offset_ns == clocks.offset_ns - 3_000_000
    clocks.round_trip(sync, 500_000, 500_000)  # a fast, even one: exact
    assert sync.offset_ns == clocks.offset_ns
    assert sync.rtt_ns == 1_000_000
    assert sync.remote_usec(2.5) == (2_500_000_000 + clocks.offset_ns) // 1000


def test_late_unknown_and_foreign_answers_are_not_used() -> None:
    clocks = Clocks()
    sync = TimeSync(max_rtt_s=0.01, clock_ns=clocks.ours)
    clocks.round_trip(sync, 20_000_000, 20_000_000)  # 40 ms: beyond the limit
    assert sync.offset_ns is None
    assert sync.handle(123, 456) is None  # answers a request we never sent
    assert sync.offset_ns is None


def test_requests_are_answered_with_our_time() -> None:
    clocks = Clocks()
    sync = TimeSync(clock_ns=clocks.ours)
    assert sync.handle(0, 777) == (clocks.ours_ns, 777)
    assert sync.answered == 1


@pytest.mark.parametrize("ours_s", [0.0, 12.345678])
def test_remote_time_is_in_microseconds(ours_s: float) -> None:
    clocks = Clocks()
    sync = TimeSync(clock_ns=clocks.ours)
    clocks.round_trip(sync, 0, 0)
    assert sync.remote_usec(ours_s) == round(ours_s * 1e6) + clocks.offset_ns // 1000


def test_negative_times_are_neither_answered_nor_used() -> None:
    """TIMESYNC's fields are times since boot: a negative one (a broken or hostile sender) is
    ignored, so no offset puts a LANDING_TARGET before the autopilot's boot."""
    clocks = Clocks()
    sync = TimeSync(clock_ns=clocks.ours)
    _, ts1 = sync.request()
    assert sync.handle(-5, ts1) is None  # an answer with a negative time
    assert sync.handle(0, -7) is None  # a request with one
    assert sync.offset_ns is None
    assert sync.ignored == 2
    clocks.offset_ns = -clocks.ours_ns - 10_000_000_000  # a clock 10 s behind our zero
    clocks.round_trip(sync, 500_000, 500_000)
    assert sync.offset_ns is None  # its answer is a negative time too
    assert sync.remote_usec(float("nan")) is None


def test_timesync_forgets_the_old_offset_when_the_autopilot_clock_restarts() -> None:
    """Ten answers put the autopilot 500 s ahead; it reboots and the next answer puts it 2 s
    ahead: the offset follows at once, not after the window has turned over."""
    now = [1_000_000_000]
    sync = TimeSync(clock_ns=lambda: now[0])

    def answer(remote_ns: int) -> None:
        _, ts1 = sync.request()
        now[0] += 2_000_000  # a 2 ms round trip
        sync.handle(remote_ns + now[0] - 1_000_000, ts1)

    for _ in range(10):
        answer(500_000_000_000)
    assert sync.offset_ns is not None
    assert abs(sync.offset_ns - 500_000_000_000) < 2_000_000
    answer(2_000_000_000)
    assert sync.offset_ns is not None
    assert abs(sync.offset_ns - 2_000_000_000) < 2_000_000
    assert sync.resets == 1
