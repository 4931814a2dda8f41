"""Race replays: a recorded race renders to a GIF with one frame per 1/fps seconds of race time."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from spiral.eval.replay import RaceRecording, frame_count, record_race, render_race
from spiral.sim import COLLISION_KINDS


def test_two_second_race_writes_a_gif_with_the_expected_frame_count(sprint, tiny_checkpoint, tmp_path):
    """Record a 2 s 1v1 race (policy vs planner) and write 2·15 + 1 = 31 frames at 15 fps."""
    rec = record_race(sprint, "1v1", ("tiny", str(tiny_checkpoint)), ("planner", "se-ibr"), seed=0)
    assert rec.duration == pytest.approx(2.0)  # the sprint's time limit: nobody finishes a lap in 2 s
    assert rec.pos.shape == (97, 2, 3)
    out = tmp_path / "race.gif"
    frames = render_race(rec, out, fps=15)
    assert frames == frame_count(2.0, 15) == 31
    with Image.open(out) as gif:
        assert gif.n_frames == 31
        assert gif.size == (800, 416)
        delays = []
        for i in range(gif.n_frames):
            gif.seek(i)
            delays.append(gif.info["duration"])
    assert sum(delays[:-1]) == 2000  # real time: 30 intervals of 1/15 s
    assert delays[-1] == 1500  # the final state is held


def test_a_recording_tells_how_each_drones_race_ended(sprint):
    """A hand-made 2v2 recording: a finisher, a drone that hit a gate frame, one that hit a drone and the ground,
    and one still racing; one line each, by slot, with its team's method."""
    steps, drones = 3, 4
    gates = np.array([[0, 0, 0, 0], [3, 1, 2, 1], [7, 2, 2, 4]])
    finished = np.zeros((steps, drones), bool)
    finished[2, 0] = True
    crashed = np.zeros((steps, drones), bool)
    crashed[1:, 1] = crashed[2, 2] = True
    kinds = np.array([0, COLLISION_KINDS["gate"], COLLISION_KINDS["drone"] | COLLISION_KINDS["ground"], 0])
    rec = RaceRecording(sprint, "2v2", ["a", "b"], 0.1, np.zeros((steps, drones, 3)), gates, crashed, finished,
                        kinds, np.array([4.12, 0.0, 0.0, 0.0]), 7)
    assert rec.outcomes() == [
        "drone 0 (a): finished in 4.12 s",
        "drone 1 (a): crashed (gate) after 2 of 7 gate passes",
        "drone 2 (b): crashed (ground, drone) after 2 of 7 gate passes",
        "drone 3 (b): still racing after 4 of 7 gate passes",
    ]


def test_replay_refuses_unknown_formats(sprint, tmp_path):
    """Reject an output suffix other than .gif and .mp4 before rendering."""
    rec = record_race(sprint, "solo", ("planner", "se-ibr"), seed=0)
    with pytest.raises(ValueError, match=r"\.gif or \.mp4"):
        render_race(rec, tmp_path / "race.avi")


@pytest.mark.parametrize("duration", [2.0, 4.1, 3.97, 0.05])
def test_replay_frames_reach_the_end_of_the_race(duration):
    """The last frame is at or past the race's end (rendered as its final state), never a frame short of it."""
    count = frame_count(duration, 15)
    assert (count - 1) / 15 >= duration - 1e-9
    assert (count - 2) / 15 < duration
