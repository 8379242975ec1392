"""A demonstrations directory: finished episodes staged one file each, a manifest naming the
run, and the Minari dataset built from them.

Layout of ``DIR``::

    manifest.json                   what generated the episodes (scenario, lockstep, format)
    episodes/seed_000123.npz        one finished episode each, written atomically
    minari/mmpc/<name>-expert-v0/   the Minari dataset (``data/main_data.hdf5``, ``metadata.json``)

Resuming: an episode file appears only complete (written to a temporary name, flushed, then
renamed), so an interrupted run leaves finished episodes and nothing half-written; a re-run
skips them. The Minari dataset is rebuilt from the staged files (into a temporary folder
swapped in at the end), so it always holds exactly the requested episodes, each once.

Loading (Minari's documented local path): ``MINARI_DATASETS_PATH=DIR/minari`` and
``minari.load_dataset("mmpc/cruise-expert-v0")``, or :func:`open_dataset` (``DIR`` in, a
``minari.MinariDataset`` out).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import shutil
import warnings
import zipfile
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Iterator, NamedTuple, Optional, Sequence

import numpy as np

from mmpc.config import from_dict, to_dict
from mmpc.files import TEMPORARY_PREFIX, atomic_write
from mmpc.imitation.rollout import INFO_FIELDS, Episode
from mmpc.road import Road
from mmpc.scenario import ScenarioConfig

logger = logging.getLogger(__name__)

FORMAT = "mmpc-demonstrations"
FORMAT_VERSION = 2  # 2: infos gained "neighbours"
MANIFEST = "manifest.json"
EPISODES = "episodes"
MINARI_ROOT = "minari"
#: Packages whose versions go into the manifest and the dataset metadata.
PACKAGES = ("mmpc", "torch", "numpy", "gymnasium", "highway-env", "minari")


class DemonstrationsError(RuntimeError):
    """A directory that is not (or not this run's) demonstrations directory, or a damaged one."""


def package_versions() -> dict[str, Optional[str]]:
    """Installed versions of :data:`PACKAGES` (``None`` where not installed)."""
    versions: dict[str, Optional[str]] = {}
    for name in PACKAGES:
        try:
            versions[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def dataset_id(scenario: ScenarioConfig) -> str:
    """Minari id of a scenario's expert dataset: ``mmpc/<scenario>-expert-v0``."""
    name = "".join(c if c.isalnum() else "_" for c in scenario.name)
    return f"mmpc/{name}-expert-v0"


#: The experts a demonstrations directory may hold (:attr:`Manifest.expert`).
EXPERTS = ("mpc", "verified:mpc")


@dataclasses.dataclass(frozen=True)
class Manifest:
    """What makes two runs' episodes the same: the scenario (seeds aside), the lockstep chunk size
    (lockstep batches round differently from single solves) and the file format.

    Attributes:
        scenario: :func:`mmpc.config.to_dict` of the scenario (its ``seeds`` are not part of it; the
            episodes' seeds are chosen on the command line). :meth:`read` returns it as this mmpc
            writes it, so that a manifest written before a scenario setting was retired (e.g.
            ``mpc.compile``, ``mpc.wheelbase``) names the same scenario.
        lockstep: episodes per lockstep chunk (chunk k holds seeds ``k * lockstep ...``).
        packages: package versions of the run that created the directory (informative only).
        expert: who drove: ``"mpc"`` (the scenario's MPC) or ``"verified:mpc"`` (the MPC behind
            :mod:`mmpc.verify`'s check).
    """

    scenario: dict
    lockstep: int
    packages: dict
    expert: str = "mpc"

    def __post_init__(self) -> None:
        if self.expert not in EXPERTS:
            raise ValueError(f"`expert` must be one of {list(EXPERTS)}; got {self.expert!r}")

    def identity(self) -> str:
        """SHA-256 of the scenario, lockstep and expert (what a resumed run must match); the MPC's
        directories hash as before the expert was recorded."""
        scenario = {k: v for k, v in self.scenario.items() if k != "seeds"}
        fields = {"scenario": scenario, "lockstep": self.lockstep, "format": FORMAT_VERSION}
        if self.expert != "mpc":
            fields["expert"] = self.expert
        return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()

    def to_json(self) -> str:
        return json.dumps({"format": FORMAT, "version": FORMAT_VERSION, "identity": self.identity(),
                           "scenario": self.scenario, "lockstep": self.lockstep, "expert": self.expert,
                           "packages": self.packages}, indent=2)

    @classmethod
    def read(cls, path: Path) -> "Manifest":
        try:
            values = json.loads(path.read_text())
            if values.get("format") != FORMAT:
                raise DemonstrationsError(f"{path}: `format` is {values.get('format')!r}, expected {FORMAT!r}")
            if values.get("version") != FORMAT_VERSION:
                raise DemonstrationsError(f"{path}: format version {values.get('version')!r}; this mmpc reads version {FORMAT_VERSION}")
            manifest = cls(values["scenario"], int(values["lockstep"]), values.get("packages", {}), values.get("expert", "mpc"))
        except (ValueError, KeyError, TypeError) as error:
            raise DemonstrationsError(f"{path} is corrupt ({type(error).__name__}: {error}); "
                                      "remove the directory or choose another --out") from error
        if values.get("identity") != manifest.identity():
            raise DemonstrationsError(f"{path} is corrupt: its identity hash does not match its contents; "
                                      "remove the directory or choose another --out")
        try:
            scenario = from_dict(ScenarioConfig, manifest.scenario, where=f"{path}: scenario")
        except (ValueError, TypeError) as error:
            raise DemonstrationsError(f"this mmpc cannot read the scenario of {path} ({error}); drive these "
                                      "demonstrations again in another --out") from error
        return dataclasses.replace(manifest, scenario=to_dict(scenario))


def save_episode(path: Path, episode: Episode) -> None:
    """Write one episode atomically as ``.npz``."""
    arrays = {
        "seed": np.int64(episode.seed),
        "observations": episode.observations,
        "actions": episode.actions,
        "rewards": episode.rewards,
        "terminations": episode.terminations,
        "truncations": episode.truncations,
        **{f"info_{name}": values for name, values in episode.infos.items()},
    }
    atomic_write(path, lambda handle: np.savez(handle, **arrays))


def load_episode(path: Path) -> Episode:
    """Read an episode written by :func:`save_episode`; a damaged file raises :class:`DemonstrationsError`."""
    try:
        with np.load(path, allow_pickle=False) as data:
            infos = {name: data[f"info_{name}"] for name in INFO_FIELDS}  # KeyError: not an episode file
            infos.update({key.removeprefix("info_"): data[key] for key in data.files if key.startswith("info_")})
            episode = Episode(int(data["seed"]), data["observations"], data["actions"], data["rewards"],
                              data["terminations"], data["truncations"], infos)
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise DemonstrationsError(f"episode file {path} is damaged ({type(error).__name__}: {error}); "
                                  "delete it and re-run to regenerate that episode") from error
    steps = episode.actions.shape[0]
    shapes_ok = (episode.observations.shape[0] == steps + 1 and episode.actions.shape == (steps, 2)
                 and all(a.shape[0] == steps for a in (episode.rewards, episode.terminations, episode.truncations))
                 and all(v.shape[0] == steps + 1 for v in infos.values()))
    if not shapes_ok:
        raise DemonstrationsError(f"episode file {path} has inconsistent array lengths; delete it and re-run")
    return episode


class DemonstrationsDir:
    """A demonstrations directory opened for one run (see the module docstring).

    Args:
        root: the directory (created when missing).
        manifest: this run's manifest. An empty or missing ``root`` gets it; an existing one
            must carry the same identity.

    Raises:
        DemonstrationsError: ``root`` holds something else (no manifest, another format, a
            corrupt manifest) or another run's episodes (different scenario or lockstep).
    """

    def __init__(self, root: Path, manifest: Manifest) -> None:
        self.root = Path(root)
        self.manifest = manifest
        path = self.root / MANIFEST
        if self.root.exists() and not self.root.is_dir():
            raise DemonstrationsError(f"--out {self.root} exists and is not a directory")
        if path.exists():
            existing = Manifest.read(path)
            if existing.identity() != manifest.identity():
                changed = [k for k in manifest.scenario if k != "seeds" and manifest.scenario[k] != existing.scenario.get(k)]
                if existing.lockstep != manifest.lockstep:
                    changed.append("lockstep")
                if existing.expert != manifest.expert:
                    changed.append(f"expert ({existing.expert} there, {manifest.expert} asked)")
                raise DemonstrationsError(
                    f"{self.root} holds demonstrations of another configuration (differs in: {', '.join(changed) or 'format'}); "
                    f"re-run with the same scenario, --lockstep and --expert ({existing.expert}) to resume, or choose "
                    "another --out")
        elif self.root.exists() and any(self.root.iterdir()):
            raise DemonstrationsError(f"{self.root} is not empty and has no {MANIFEST}: it is not an mmpc demonstrations "
                                      "directory; refusing to write into it (choose another --out)")
        else:
            self.root.mkdir(parents=True, exist_ok=True)
            atomic_write(path, lambda handle: handle.write(manifest.to_json().encode()))
        self.episodes_dir.mkdir(exist_ok=True)
        for stale in self.episodes_dir.glob(f"{TEMPORARY_PREFIX}*"):  # left by a process killed mid-write
            stale.unlink()

    @property
    def episodes_dir(self) -> Path:
        return self.root / EPISODES

    def episode_path(self, seed: int) -> Path:
        return self.episodes_dir / f"seed_{seed:06d}.npz"

    def finished_seeds(self) -> set[int]:
        """Seeds whose episode file is present."""
        seeds = set()
        for path in self.episodes_dir.glob("seed_*.npz"):
            try:
                seeds.add(int(path.stem.removeprefix("seed_")))
            except ValueError as error:
                raise DemonstrationsError(f"unexpected file {path} in {self.episodes_dir}") from error
        return seeds

    def write(self, episode: Episode) -> Path:
        path = self.episode_path(episode.seed)
        save_episode(path, episode)
        return path

    def read(self, seed: int) -> Episode:
        return load_episode(self.episode_path(seed))


def minari_dataset_path(root: Path, scenario_name_or_id: str) -> Path:
    """Folder of the Minari dataset (the one holding ``data/``) inside a demonstrations directory."""
    identifier = scenario_name_or_id if "/" in scenario_name_or_id else f"mmpc/{scenario_name_or_id}-expert-v0"
    return Path(root) / MINARI_ROOT / identifier


@contextlib.contextmanager
def _datasets_path(path: Path) -> Iterator[None]:
    """Point Minari's ``MINARI_DATASETS_PATH`` at ``path`` for the duration."""
    previous = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(Path(path).resolve())  # Minari mis-joins relative roots
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = previous


def _require_minari():
    try:
        import minari
    except ImportError as error:
        raise ImportError("Minari datasets need the optional extra: pip install 'mmpc[datasets]'") from error
    return minari


#: What every dataset's description says about its arrays (after a first sentence on who drove).
DATASET_ARRAYS = (
    "Observations: highway-env's Kinematics observation; actions: executed (acceleration [m/s^2], steering [rad]) "
    "(highway-env's [-1, 1] action scaled by its ranges); infos[t]: the decision at observations[t] (goal index, "
    "plan and meta cost, solver residuals, road-frame ego state and nearest 8 vehicles), last row -1/NaN. The env spec "
    "rebuilds highway-env with the scenario's config; mmpc's traffic controller (slow target speeds, "
    "respawn window) is in the metadata's mmpc_scenario, applied by mmpc.highway.HighwayEpisode."
)


def build_minari(directory: DemonstrationsDir, scenario: ScenarioConfig, seeds: Sequence[int], *,
                 identifier: Optional[str] = None, driver: str = "mmpc multi-modal MPC expert",
                 description: Optional[str] = None):
    """(Re)build the Minari dataset of ``directory`` from the staged episodes of ``seeds``.

    The dataset is written under a temporary folder and swapped in, so an interrupted build
    leaves the previous dataset (or none) and the staged episodes intact.

    Args:
        directory: the demonstrations directory.
        scenario: the scenario the episodes were driven in (for the env spec and metadata).
        seeds: the episodes to include, in this order (all must be staged).
        identifier: the Minari id (default :func:`dataset_id`, the expert's demonstrations).
        driver: who drove (Minari's ``algorithm_name``).
        description: what the dataset holds beyond :data:`DATASET_ARRAYS` (default: the MPC's demonstrations).

    Returns:
        The ``minari.MinariDataset``.
    """
    minari = _require_minari()
    import gymnasium as gym
    from gymnasium import spaces
    from minari.data_collector import EpisodeBuffer

    from mmpc.highway import ACCELERATION_RANGE, STEERING_RANGE, env_config

    missing = sorted(set(seeds) - directory.finished_seeds())
    if missing:
        raise DemonstrationsError(f"cannot build the dataset: episodes of seeds {missing[:10]} are not staged")
    identifier = dataset_id(scenario) if identifier is None else identifier
    episodes = [directory.read(seed) for seed in seeds]
    buffers = [
        EpisodeBuffer(id=index, seed=episode.seed, observations=episode.observations, actions=episode.actions,
                      rewards=episode.rewards, terminations=episode.terminations, truncations=episode.truncations,
                      infos=dict(episode.infos))
        for index, episode in enumerate(episodes)
    ]
    observation_shape = episodes[0].observations.shape[1:]
    env = gym.make(scenario.env_id, config=env_config(scenario))  # its spec (with the config) goes into the dataset
    building = directory.root / ".minari-building"
    shutil.rmtree(building, ignore_errors=True)
    with _datasets_path(building), warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # no code permalink / author: not errors
        dataset = minari.create_dataset_from_buffers(
            dataset_id=identifier,
            buffer=buffers,
            env=env,
            algorithm_name=driver,
            observation_space=spaces.Box(-np.inf, np.inf, shape=observation_shape, dtype=np.float32),
            action_space=spaces.Box(np.array([ACCELERATION_RANGE[0], STEERING_RANGE[0]], dtype=np.float32),
                                    np.array([ACCELERATION_RANGE[1], STEERING_RANGE[1]], dtype=np.float32)),
            description=(description or f"Multi-modal MPC (mmpc) driving highway-env scenario '{scenario.name}'.")
            + " " + DATASET_ARRAYS,
            data_format="hdf5",
            requirements=[f"mmpc=={package_versions()['mmpc']}"],
        )
        dataset.storage.update_metadata({
            "mmpc_scenario": to_dict(scenario),
            "mmpc_seeds": [int(s) for s in seeds],
            "mmpc_lockstep": directory.manifest.lockstep,
            "mmpc_expert": directory.manifest.expert,
            "mmpc_packages": package_versions(),
        })
    env.close()
    target = directory.root / MINARI_ROOT
    retired = directory.root / ".minari-retired"
    shutil.rmtree(retired, ignore_errors=True)
    if target.exists():
        os.replace(target, retired)
    os.replace(building, target)
    shutil.rmtree(retired, ignore_errors=True)
    return open_dataset(directory.root, identifier)


def built_seeds(root: Path, identifier: str) -> Optional[list[int]]:
    """Seeds of the dataset already built in ``root`` (``None``: none built or unreadable)."""
    path = Path(root) / MINARI_ROOT / identifier / "data" / "metadata.json"
    try:
        return [int(s) for s in json.loads(path.read_text())["mmpc_seeds"]]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def open_dataset(root: Path, identifier: Optional[str] = None):
    """The Minari dataset in demonstrations directory ``root``.

    Args:
        root: the ``--out`` folder of ``mmpc imitate demos``.
        identifier: the dataset id (default: the only one there).

    Returns:
        ``minari.MinariDataset``.
    """
    minari = _require_minari()
    base = Path(root) / MINARI_ROOT
    if identifier is None:
        found = sorted(p.parent.relative_to(base).as_posix() for p in base.glob("*/*/data")) if base.is_dir() else []
        if len(found) != 1:
            raise DemonstrationsError(f"{root}: expected one Minari dataset under {base}; found {found or 'none'} "
                                      "(run `mmpc imitate demos --out` to completion first)")
        identifier = found[0]
    with _datasets_path(base):
        return minari.load_dataset(identifier)


class Transitions(NamedTuple):
    """State-action pairs for supervised learning, in the road-frame form the policy reads.

    Fields:
        ego: (S, 6) float32 ego states (:data:`mmpc.EGO_FIELDS`) at which an action was taken.
        neighbours: (S, K, 4) float32 nearest other vehicles there (x, y, vx, vy; NaN rows:
            empty slots; :func:`mmpc.imitation.features.nearest_neighbours`).
        actions: (S, 2) float32 the expert's (acceleration [m/s^2], steering [rad]).
        episodes: (S,) int64 index of the episode each pair came from (for held-out splits).
    """

    ego: np.ndarray
    neighbours: np.ndarray
    actions: np.ndarray
    episodes: np.ndarray

    @classmethod
    def concatenate(cls, parts: Sequence["Transitions"]) -> "Transitions":
        return cls(*(np.concatenate([getattr(p, name) for p in parts]) for name in cls._fields))


def dataset_transitions(dataset) -> Transitions:
    """All (state, action) pairs of a Minari dataset (the final state of each episode, which has
    no action, is left out)."""
    parts = []
    for episode in dataset.iterate_episodes():
        steps = len(episode.actions)
        parts.append(Transitions(np.asarray(episode.infos["ego"][:steps], dtype=np.float32),
                                 np.asarray(episode.infos["neighbours"][:steps], dtype=np.float32),
                                 np.asarray(episode.actions, dtype=np.float32),
                                 np.full(steps, episode.id, dtype=np.int64)))
    if not parts:
        raise DemonstrationsError("the dataset holds no episodes")
    return Transitions.concatenate(parts)


def dataset_road(dataset) -> Road:
    """The road of the scenario a dataset was driven in (its ``mmpc_scenario`` metadata)."""
    return from_dict(ScenarioConfig, dataset.storage.metadata["mmpc_scenario"], where="dataset metadata: mmpc_scenario").road
