"""NGSIM trajectory reader and replay, on a small file in the public US-101 / I-80 CSV layout."""

import csv

import numpy as np
import pytest

from mmpc.highway.runner import run_episode
from mmpc.drivers import make_driver
from mmpc.highway import HighwayEpisode
from mmpc.highway.ngsim import FOOT, read_ngsim
from mmpc.scenario import EgoConfig, ScenarioConfig
from mmpc.traffic_config import NGSIMTraffic
from mmpc.highway.traffic import ReplayVehicle

#: The column order of the data.gov release (US-101 and I-80 files).
COLUMNS = [
    "Vehicle_ID", "Frame_ID", "Total_Frames", "Global_Time", "Local_X", "Local_Y", "Global_X", "Global_Y",
    "v_length", "v_Width", "v_Class", "v_Vel", "v_Acc", "Lane_ID", "O_Zone", "D_Zone", "Int_ID", "Section_ID",
    "Direction", "Movement", "Preceding", "Following", "Space_Headway", "Time_Headway", "Location",
]
T0_MS = 1118846979700  # a US-101 Global_Time
LANE_FT = 12.0


def lane_x(lane: float) -> float:
    """Local_X [ft] of a lane's centre (lane 1 = leftmost)."""
    return (lane - 0.5) * LANE_FT


def write_ngsim(path, vehicles, location="us-101"):
    """vehicles: (id, first frame, frames, front Local_Y [ft] at the first frame, speed [ft/s], lane(t) callable)."""
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(COLUMNS)
        for vid, first, frames, y0, speed, lane in vehicles:
            for k in range(frames):
                t = k / 10.0
                frame = first + k
                writer.writerow([
                    vid, frame, frames, T0_MS + 100 * frame, f"{lane_x(lane(t)):.3f}", f"{y0 + speed * t:.3f}",
                    6451000.0, 1873000.0, 15.0, 6.0, 2, speed, 0.0, round(lane(t)), 101, 201, 0, 0, 2, 1, 0, 0,
                    50.0, 2.0, location,
                ])
    return path


def constant(lane):
    return lambda t: lane


@pytest.fixture
def ngsim_file(tmp_path):
    """60 s at 10 Hz: three cars from the start, one entering at 10 s, one changing lanes, one leaving at 20 s."""
    return write_ngsim(tmp_path / "trajectories.csv", [
        (1, 0, 600, 300.0, 30.0, constant(2)),
        (2, 0, 600, 200.0, 40.0, constant(3)),
        (3, 0, 600, 600.0, 25.0, constant(1)),
        (4, 100, 500, 0.0, 45.0, constant(2)),
        (5, 0, 600, 100.0, 35.0, lambda t: 4.0 - min(max((t - 20.0) / 4.0, 0.0), 1.0)),
        (6, 0, 200, 700.0, 30.0, constant(5)),
    ])


def test_tracks_are_in_metres_on_highway_env_lanes(ngsim_file):
    recording = read_ngsim(ngsim_file)
    assert len(recording.tracks) == 6 and recording.duration == pytest.approx(59.9)
    first = next(t for t in recording.tracks if t.vehicle_id == 1)
    assert first.time[0] == 0.0 and first.time[-1] == pytest.approx(59.9)
    assert first.x[0] == pytest.approx((300.0 - 7.5) * FOOT)  # the centre: front minus half the length
    assert first.y[0] == pytest.approx(4.0)  # NGSIM lane 2 -> highway-env lane 1 at y = 4 m
    assert first.vx[10] == pytest.approx(30.0 * FOOT) and first.vy[10] == pytest.approx(0.0, abs=1e-9)
    assert (first.length, first.width) == pytest.approx((15.0 * FOOT, 6.0 * FOOT))
    lanes = {t.vehicle_id: t.y[0] for t in recording.tracks}
    assert lanes[3] == pytest.approx(0.0) and lanes[6] == pytest.approx(16.0)


def test_lane_change_gives_lateral_velocity_and_tracks_start_in_order(ngsim_file):
    recording = read_ngsim(ngsim_file)
    assert [t.start for t in recording.tracks] == sorted(t.start for t in recording.tracks)
    changer = next(t for t in recording.tracks if t.vehicle_id == 5)
    assert changer.y[0] == pytest.approx(12.0) and changer.y[-1] == pytest.approx(8.0)
    assert changer.state_at(22.0)[3] == pytest.approx(-4.0 / 4.0, rel=0.05)  # one lane (4 m) in 4 s, leftwards
    assert len(recording.active(5.0)) == 5 and len(recording.active(30.0)) == 5


def test_reused_vehicle_ids_split_into_tracks(tmp_path):
    path = write_ngsim(tmp_path / "reuse.csv", [(7, 0, 50, 0.0, 30.0, constant(1)), (7, 200, 50, 0.0, 30.0, constant(3))])
    tracks = read_ngsim(path).tracks
    assert len(tracks) == 2 and tracks[1].start == pytest.approx(20.0)


def test_location_filter(tmp_path):
    path = tmp_path / "combined.csv"
    write_ngsim(path, [(1, 0, 30, 0.0, 30.0, constant(1))], location="us-101")
    with open(path, "a", newline="") as handle:
        rows = list(csv.reader(open(write_ngsim(tmp_path / "i80.csv", [(2, 0, 30, 0.0, 30.0, constant(2))], "i-80"))))[1:]
        csv.writer(handle).writerows(rows)
    assert [t.vehicle_id for t in read_ngsim(path, location="I-80").tracks] == [2]
    assert len(read_ngsim(path).tracks) == 2
    with pytest.raises(ValueError, match="peachtree"):
        read_ngsim(path, location="peachtree")


def test_bad_files_are_reported(tmp_path):
    missing_column = tmp_path / "missing.csv"
    missing_column.write_text("Vehicle_ID,Frame_ID,Global_Time,Local_X,Local_Y,v_Vel,v_Acc,Lane_ID,v_Length\n1,1,0,6,0,30,0,1,15\n")
    with pytest.raises(ValueError, match="v_Width"):
        read_ngsim(missing_column)
    bad_value = tmp_path / "bad.csv"
    bad_value.write_text(",".join(COLUMNS) + "\n" + ",".join(["x"] * len(COLUMNS)) + "\n")
    with pytest.raises(ValueError, match="line 2"):
        read_ngsim(bad_value)
    with pytest.raises(FileNotFoundError, match="README"):
        read_ngsim(tmp_path / "nowhere.csv")


def ngsim_scenario(path, **traffic) -> ScenarioConfig:
    values = dict(path=str(path), start_time=5.0, ego_position=60.0, initial_clearance=15.0)
    values.update(traffic)
    return ScenarioConfig(name="ngsim", duration=8.0, ego=EgoConfig(speed=12.0, lane=2), traffic=NGSIMTraffic(**values))


@pytest.mark.usefixtures("one_thread")
def test_replay_follows_the_recording_and_vehicles_come_and_go(ngsim_file):
    recording = read_ngsim(ngsim_file)
    scenario = ngsim_scenario(ngsim_file, start_time=15.0)
    episode, mpc = HighwayEpisode(scenario, seed=0), make_driver("mpc", scenario)
    try:
        shift = episode.ego.position[0] - 60.0
        replayed = {v.track.vehicle_id: v for v in episode.unwrapped.road.vehicles if isinstance(v, ReplayVehicle)}
        assert set(replayed) == {1, 2, 3, 4, 5, 6}
        for _ in range(60):  # 6 s: vehicle 6 (recorded until 19.9 s) leaves
            episode.step(mpc)
        replayed = {v.track.vehicle_id: v for v in episode.unwrapped.road.vehicles if isinstance(v, ReplayVehicle)}
        assert set(replayed) == {1, 2, 3, 4, 5}
        track = next(t for t in recording.tracks if t.vehicle_id == 2)
        x, y, _, _ = track.state_at(21.0)
        assert replayed[2].position == pytest.approx(np.array([x + shift, y]), abs=1e-6)
    finally:
        episode.close()


@pytest.mark.usefixtures("one_thread")
def test_vehicles_at_the_ego_start_are_left_out_and_late_ones_enter(ngsim_file):
    # The ego starts 5 m ahead of vehicle 1 in its lane (NGSIM lane 2 = highway-env lane 1).
    recording = read_ngsim(ngsim_file)
    car = next(t for t in recording.tracks if t.vehicle_id == 1)
    scenario = ngsim_scenario(ngsim_file, ego_position=float(car.state_at(5.0)[0]) + 5.0)
    scenario = scenario.replace(ego=EgoConfig(speed=12.0, lane=1))
    episode, mpc = HighwayEpisode(scenario, seed=0), make_driver("mpc", scenario)
    try:
        ids = {v.track.vehicle_id for v in episode.unwrapped.road.vehicles if isinstance(v, ReplayVehicle)}
        assert 1 not in ids and 4 not in ids  # overlapping the ego; not yet recorded
        for _ in range(55):
            episode.step(mpc)
        ids = {v.track.vehicle_id for v in episode.unwrapped.road.vehicles if isinstance(v, ReplayVehicle)}
        assert 4 in ids
    finally:
        episode.close()


@pytest.mark.usefixtures("one_thread")
def test_mpc_drives_through_replayed_traffic(ngsim_file):
    result = run_episode(ngsim_scenario(ngsim_file), seed=0)
    assert result.metrics["collisions"] == 0 and result.metrics["offroad"] == 0
    assert result.metrics["steps"] == 80 and result.metrics["mean_speed"] > 10.0


def test_replay_longer_than_the_recording_is_an_error(ngsim_file):
    with pytest.raises(ValueError, match="exceeds the recording"):
        HighwayEpisode(ngsim_scenario(ngsim_file, start_time=55.0), seed=0)
