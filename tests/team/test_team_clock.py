"""The launcher's team clock: fault windows in team stream time, also after the streams end."""

from kimera_multi_py.team.launcher import RobotView, TeamClock


def _views(*states: tuple[float, bool]) -> dict[str, RobotView]:
    return {f"robot{r}": RobotView(stamp=s, finished=f) for r, (s, f) in enumerate(states)}


def test_streams_set_the_time_while_they_run():
    clock = TeamClock(rate=4.0)
    assert clock.now(_views((10.0, False), (12.0, False)), {0, 1}, wall=100.0) == 12.0
    assert clock.now(_views((75.0, True), (40.0, False)), {0, 1}, wall=150.0) == 75.0  # robot 1 still streams


def test_after_the_streams_end_it_runs_on_at_the_launch_rate():
    clock = TeamClock(rate=4.0)
    assert clock.now(_views((75.0, True), (75.0, True)), {0, 1}, wall=200.0) == 75.0
    assert clock.now(_views((75.0, True), (75.0, True)), {0, 1}, wall=202.5) == 85.0
    unbounded = TeamClock(rate=float("inf"))  # as fast as possible: real time after the end
    unbounded.now(_views((75.0, True)), {0}, wall=10.0)
    assert unbounded.now(_views((75.0, True)), {0}, wall=13.0) == 78.0


def test_a_robot_cut_off_does_not_hold_it_and_one_heard_again_does_not_turn_it_back():
    clock = TeamClock(rate=2.0)
    cut = _views((75.0, True), (30.0, False))  # robot 1's link is cut: its view is stale
    assert clock.now(cut, {0}, wall=0.0) == 75.0
    assert clock.now(cut, {0}, wall=5.0) == 85.0  # the window can end after the streams
    # healed: robot 1 is heard again, its old state not yet replaced: the clock waits, never back
    assert clock.now(cut, {0, 1}, wall=6.0) == 85.0
    assert clock.now(_views((75.0, True), (75.0, True)), {0, 1}, wall=7.0) == 85.0
    assert clock.now(_views((75.0, True), (75.0, True)), {0, 1}, wall=8.0) == 87.0
