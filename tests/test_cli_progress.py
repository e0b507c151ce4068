"""Progress of long commands: a total and an estimate of the time left, a line every few seconds when
not on a terminal, calibration rounds shown against their bound (``round k of ≤ N``)."""

from __future__ import annotations

import io
from types import SimpleNamespace

from cloud.daemon.epochs import Epochs
from cloud.daemon.settings import CloudSettings
from shared.progress import Progress, format_seconds
from simfleet.run import Eta


class Clock:
    """A clock the test moves."""

    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class Pipe(io.StringIO):
    def isatty(self) -> bool:
        return False


class Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_not_on_a_terminal_a_line_every_few_seconds_with_the_total_and_the_time_left():
    clock, out = Clock(), Pipe()
    with Progress(40, "passes", stream=out, unit="acked", every_s=5.0, clock=clock) as bar:
        for done in range(1, 41):
            clock.t += 1.0  # one pass a second
            bar.update(done)
    lines = out.getvalue().splitlines()
    # the opening line, one every 5 s of the 40 s, and the closing line
    assert len(lines) == 1 + 8 + 1, lines
    assert lines[0].startswith("passes 0/40 acked")
    assert lines[1] == "passes 5/40 acked, ~35 s left, 5 s so far"  # 35 passes at one a second
    assert lines[-1] == "passes 40/40 acked in 40.0 s"


def test_on_a_terminal_one_line_redrawn_in_place():
    clock, out = Clock(), Tty()
    with Progress(3, "sim", stream=out, clock=clock) as bar:
        for _ in range(3):
            clock.t += 1.0
            bar.advance()
    text = out.getvalue()
    redraws = text.split("\r")[1:]
    assert text.count("\n") == 1 and len(redraws) == 5, text
    assert redraws[1] == "sim 1/3, ~2 s left, 1 s so far"
    assert redraws[-1].rstrip() == "sim 3/3 in 3.0 s"  # padded: what the longer line before left is blanked


def test_silent_when_disabled():
    out = Tty()
    with Progress(3, "sim", stream=out, enabled=False) as bar:
        bar.advance(3)
    assert out.getvalue() == ""


def test_the_callers_estimate_and_note_win_over_the_rate():
    clock, out = Clock(), Pipe()
    with Progress(10, "passes", stream=out, unit="acked", every_s=5.0, clock=clock) as bar:
        clock.t += 6.0
        bar.update(10, note="calibration round 3 of ≤ 24", left_s=130.0)
    assert out.getvalue().splitlines()[1] == "passes 10/10 acked, calibration round 3 of ≤ 24, ~2 min left, 6 s so far"
    assert format_seconds(0.2) == "~1 s" and format_seconds(89) == "~89 s" and format_seconds(150) == "~2 min"


def test_eta_passes_then_rounds_bounded():
    eta = Eta()
    note, left = eta.update(0.0, 0, 10, 0, 0)
    assert note == "0 calibration rounds" and left is None
    note, left = eta.update(10.0, 5, 10, 1, 12)
    assert note == "1 calibration round" and left == 10.0  # 5 more passes at 2 s each
    note, left = eta.update(20.0, 10, 10, 2, 10)
    # rounds seen at t = 10 and 20: 10 s a round, at most 10 rounds left
    assert note == "calibration round 2 of ≤ 12" and left == 100.0
    note, left = eta.update(25.0, 10, 10, 4, 0)
    assert note == "calibration rounds done, finishing estimates" and left is None


def _epochs(n_passes: int, size: int, rounds: int, round0: int, dirty: bool = True) -> Epochs:
    calibrator = SimpleNamespace(max_rounds=12, min_passes=3, rounds=rounds, dirty=dirty, settled=False,
                                 budget_from=round0)
    ep = Epochs(calibrator, CloudSettings(calibration="fleet"), clock=lambda: 0.0)
    ep.restore_order([(f"v{i}", f"p{i}") for i in range(n_passes)])
    ep.size, ep.round0 = size, round0
    return ep


def test_rounds_left_max_is_the_budget_of_the_current_epoch_and_of_each_epoch_still_due():
    # the settings' boundaries: 8 passes, then doubling (the step capped at 64)
    assert _epochs(2, 0, 0, 0).rounds_left_max() == 0  # too few passes for a round
    assert _epochs(5, 0, 0, 0).rounds_left_max() == 12  # one epoch (a tail of 5) due
    assert _epochs(10, 0, 0, 0).rounds_left_max() == 24  # epochs of 8, then 10
    assert _epochs(10, 8, 5, 0).rounds_left_max() == 7 + 12  # 5 of the first epoch's 12 ran; 10 still due
    assert _epochs(10, 8, 5, 0, dirty=False).rounds_left_max() == 12  # the first epoch ended (nobody moved)
    assert _epochs(40, 8, 12, 0).rounds_left_max() == 3 * 12  # 16, 32, 40 still due
    assert _epochs(10, 10, 30, 24, dirty=False).rounds_left_max() == 0  # all passes in a finished epoch
