"""Read NGSIM vehicle trajectories (US-101 / I-80 CSV format) into per-vehicle tracks.

The public NGSIM "Vehicle Trajectories and Supporting Data" files have one row per vehicle
and frame (10 Hz) with, among others, the columns ``Vehicle_ID, Frame_ID, Global_Time,
Local_X, Local_Y, v_Vel, v_Acc, Lane_ID, v_Length, v_Width`` (lengths in feet, speeds in
ft/s, ``Global_Time`` in ms). ``Local_Y`` runs along the direction of travel, ``Local_X``
across it from the left edge; ``Lane_ID`` 1 is the leftmost lane. Column names are matched
case-insensitively (the releases spell ``v_Length`` / ``v_length`` differently).

``Local_X, Local_Y`` locate the front centre of the vehicle. Tracks come out in a road frame
with highway-env's lane layout: x = ``Local_Y - v_Length / 2`` [m] (the vehicle's centre) and
lateral positions scaled so that NGSIM lane k's centre lies on highway-env lane k - 1's centre,
``y = (Local_X / lane_width_ft - 1/2) * road_lane_width``. Velocities are finite differences of
the positions (the recorded ``v_Vel`` has no lateral part).
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import NamedTuple, Optional

import numpy as np

#: Metres per foot.
FOOT = 0.3048
#: Columns that must be present.
REQUIRED_COLUMNS = (
    "Vehicle_ID", "Frame_ID", "Global_Time", "Local_X", "Local_Y", "v_Vel", "v_Acc", "Lane_ID", "v_Length", "v_Width",
)
#: A vehicle's rows more than this apart in time start a new track (IDs are reused) [s].
_TRACK_GAP = 1.0


class Track(NamedTuple):
    """One recorded vehicle in the road frame.

    Fields (T samples, increasing time):
        vehicle_id: NGSIM ``Vehicle_ID``.
        time: (T,) seconds since the recording's first frame [s].
        x, y: (T,) position of the vehicle's centre [m].
        vx, vy: (T,) velocity [m/s].
        lane: (T,) NGSIM ``Lane_ID``.
        length, width: vehicle size [m].
    """

    vehicle_id: int
    time: np.ndarray
    x: np.ndarray
    y: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    lane: np.ndarray
    length: float
    width: float

    @property
    def start(self) -> float:
        return float(self.time[0])

    @property
    def end(self) -> float:
        return float(self.time[-1])

    def state_at(self, t: float) -> np.ndarray:
        """(4,) x, y [m], vx, vy [m/s] linearly interpolated at time ``t`` (clamped to the track)."""
        return np.array([np.interp(t, self.time, field) for field in (self.x, self.y, self.vx, self.vy)])


class Recording(NamedTuple):
    """All tracks of a file.

    Fields:
        tracks: tracks sorted by start time.
        duration: time from the first to the last frame [s].
    """

    tracks: tuple[Track, ...]
    duration: float

    def active(self, t: float) -> list[Track]:
        """Tracks recorded at time ``t`` [s]."""
        return [track for track in self.tracks if track.start <= t <= track.end]


def _column_map(header: list[str], path: Path) -> dict[str, int]:
    lower = {name.strip().lower(): i for i, name in enumerate(header)}
    missing = [name for name in REQUIRED_COLUMNS if name.lower() not in lower]
    if missing:
        raise ValueError(f"NGSIM file {path}: missing column(s) {missing}; expected at least {list(REQUIRED_COLUMNS)}")
    columns = {name: lower[name.lower()] for name in REQUIRED_COLUMNS}
    if "location" in lower:
        columns["Location"] = lower["location"]
    return columns


def read_ngsim(
    path: str | Path,
    *,
    location: Optional[str] = None,
    lane_width_ft: float = 12.0,
    road_lane_width: float = 4.0,
) -> Recording:
    """Read an NGSIM trajectory CSV.

    Args:
        path: the CSV file.
        location: keep only rows whose ``Location`` column equals this (case-insensitive);
            ``None`` keeps all rows.
        lane_width_ft: NGSIM lane width [ft] (12 ft on US-101 and I-80).
        road_lane_width: lane width of the road frame [m].

    Returns:
        A :class:`Recording`; time 0 is the earliest ``Global_Time`` kept.

    Raises:
        FileNotFoundError: no such file.
        ValueError: a required column is missing, a value does not parse, or no row is left.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"NGSIM file not found: {path} (see README, 'NGSIM replay')")
    if not lane_width_ft > 0 or not road_lane_width > 0:
        raise ValueError(f"`lane_width_ft` and `road_lane_width` must be > 0; got {lane_width_ft}, {road_lane_width}")
    with open(path, newline="", encoding="utf-8") as handle:
        reader = csv.reader(handle)
        try:
            header = next(reader)
        except StopIteration:
            raise ValueError(f"NGSIM file {path} is empty") from None
        columns = _column_map(header, path)
        names = REQUIRED_COLUMNS
        wanted = location.strip().lower() if location is not None else None
        if wanted is not None and "Location" not in columns:
            raise ValueError(f"NGSIM file {path}: `location` {location!r} given but the file has no Location column")
        rows = []
        for line_number, row in enumerate(reader, start=2):
            if not row:
                continue
            if wanted is not None and row[columns["Location"]].strip().lower() != wanted:
                continue
            try:
                rows.append([float(row[columns[name]]) for name in names])
            except (ValueError, IndexError) as error:
                raise ValueError(f"NGSIM file {path}, line {line_number}: cannot parse {row!r} ({error})") from None
    if not rows:
        raise ValueError(f"NGSIM file {path}: no rows" + (f" with Location {location!r}" if location else ""))
    data = np.asarray(rows, dtype=np.float64)
    field = {name: data[:, i] for i, name in enumerate(names)}
    time = (field["Global_Time"] - field["Global_Time"].min()) / 1000.0
    x = (field["Local_Y"] - 0.5 * field["v_Length"]) * FOOT
    y = (field["Local_X"] / lane_width_ft - 0.5) * road_lane_width
    tracks = []
    order = np.lexsort((field["Frame_ID"], field["Vehicle_ID"]))
    ids = field["Vehicle_ID"][order]
    for vehicle_rows in np.split(order, np.flatnonzero(np.diff(ids)) + 1):
        t = time[vehicle_rows]
        keep = np.concatenate([[True], np.diff(t) > 0])  # drop duplicated frames
        vehicle_rows, t = vehicle_rows[keep], t[keep]
        for piece in np.split(np.arange(len(t)), np.flatnonzero(np.diff(t) > _TRACK_GAP) + 1):
            tracks.append(_track(field, vehicle_rows[piece], t[piece], x, y))
    tracks.sort(key=lambda track: track.start)
    return Recording(tuple(tracks), float(time.max()))


def _track(field: dict, rows: np.ndarray, t: np.ndarray, x: np.ndarray, y: np.ndarray) -> Track:
    px, py = x[rows], y[rows]
    if len(t) > 1:
        vx, vy = np.gradient(px, t), np.gradient(py, t)
    else:
        vx, vy = field["v_Vel"][rows] * FOOT, np.zeros(1)
    return Track(
        vehicle_id=int(field["Vehicle_ID"][rows[0]]),
        time=t,
        x=px,
        y=py,
        vx=vx,
        vy=vy,
        lane=field["Lane_ID"][rows].astype(np.int64),
        length=float(field["v_Length"][rows[0]] * FOOT),
        width=float(field["v_Width"][rows[0]] * FOOT),
    )
