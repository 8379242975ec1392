"""Episode video: highway-env's frames with the driver's candidate trajectories drawn in.

Each frame is highway-env's own rendering of the state the driver decided from; on top of it
go every candidate of that decision (feasible: blue, infeasible: grey), the goals (dots) and the
executed one (red, thick).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

# highway-env's viewer opens a pygame display; SDL, left to pick its video driver, tries Wayland
# and prints "error: XDG_RUNTIME_DIR is invalid or not set" where there is no session. The video
# is read from the drawn surface, so SDL's offscreen driver is all it needs (unless one is set).
os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")

import imageio.v2 as imageio  # noqa: E402
import numpy as np  # noqa: E402
import pygame  # noqa: E402

from mmpc.drivers import Candidates
from mmpc.highway.episode import HighwayEpisode

FEASIBLE = (70, 150, 255)
INFEASIBLE = (165, 165, 165)
BEST = (230, 30, 30)


def render_candidates(episode: HighwayEpisode, candidates: Optional[Candidates]) -> np.ndarray:
    """(H, W, 3) uint8 frame of the current state with the candidates of environment 0 drawn.

    The episode's environment must have been created with ``render=True``. Drivers that plan
    nothing (``candidates`` None) get highway-env's frame alone.
    """
    episode.env.render()  # highway-env draws road and vehicles onto its viewer's surface
    viewer = episode.unwrapped.viewer
    if candidates is None:
        return viewer.get_image()
    surface = viewer.sim_surface
    world = episode.frame.to_world(candidates.xy[0].cpu().numpy())  # (K, N, 2)
    feasible = candidates.feasible[0].cpu().numpy()
    best = int(candidates.best[0])
    for k in np.argsort(feasible, kind="stable"):  # infeasible first, underneath
        if k == best:
            continue
        points = [surface.vec2pix(p) for p in world[k]]
        pygame.draw.lines(surface, FEASIBLE if feasible[k] else INFEASIBLE, False, points, 1)
    if candidates.goals is not None:
        for goal in episode.frame.to_world(candidates.goals[0].cpu().numpy()):
            pygame.draw.circle(surface, (40, 40, 40), surface.vec2pix(goal), 2)
    pygame.draw.lines(surface, BEST, False, [surface.vec2pix(p) for p in world[best]], 3)
    return viewer.get_image()


class VideoWriter:
    """Frames to ``path``: ``.mp4`` (H.264 through imageio-ffmpeg) or ``.gif``.

    Args:
        path: output file; its suffix picks the format.
        fps: frames per second (the control rate plays the episode in real time).
    """

    def __init__(self, path: str | Path, fps: float) -> None:
        self.path = Path(path)
        if self.path.suffix not in (".mp4", ".gif"):
            raise ValueError(f"`path` must end in .mp4 or .gif; got {self.path.name!r}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.suffix == ".mp4":
            self._writer = imageio.get_writer(self.path, fps=fps, codec="libx264", quality=6, macro_block_size=16)
        else:
            self._writer = imageio.get_writer(self.path, duration=1000.0 / fps, loop=0)

    def add(self, frame: np.ndarray) -> None:
        self._writer.append_data(frame)

    def close(self) -> None:
        self._writer.close()

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
