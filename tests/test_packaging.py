"""The wheel carries the shipped YAML configs: a non-editable install finds them by name.

The README installs in editable mode, where ``configs/`` is the checkout's folder; ``pip install
mmpc`` from a wheel has no checkout, so the configs must travel inside the package
(``mmpc.configs``). This builds the wheel from a copy of the sources, unpacks it and loads every
shipped config by name in a subprocess that cannot see the checkout.
"""
import json
import os
import shutil
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest

from mmpc.configs import KINDS, shipped_config_dir

REPO = Path(__file__).resolve().parents[1]
SOURCES = ("pyproject.toml", "README.md", "mmpc", "rl", "imitation", "configs")


def yaml_names(folder: Path) -> list[str]:
    return sorted(p.stem for p in folder.glob("*.yaml"))


def shipped_names() -> dict[str, list[str]]:
    return {kind: yaml_names(shipped_config_dir(kind)) for kind in KINDS}


def test_every_config_folder_is_a_known_kind_and_holds_yaml():
    folders = sorted(p.name for p in (REPO / "configs").iterdir() if p.is_dir() and p.name != "__pycache__")
    assert folders == sorted(KINDS)
    assert all(shipped_names()[kind] for kind in KINDS)
    with pytest.raises(ValueError, match="expected one of"):
        shipped_config_dir("scenario")


@pytest.fixture(scope="module")
def installed_wheel(tmp_path_factory) -> Path:
    pytest.importorskip("setuptools", reason="building the wheel without network needs setuptools")
    work = tmp_path_factory.mktemp("wheel")
    source = work / "source"
    source.mkdir()
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, source / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(REPO / name, source / name)
    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(work / "dist"), str(source)],
        capture_output=True, text=True, timeout=300,
    )
    assert built.returncode == 0, built.stderr
    (wheel,) = (work / "dist").glob("mmpc-*.whl")
    site = work / "site"
    with zipfile.ZipFile(wheel) as archive:
        archive.extractall(site)
    return site


def test_wheel_ships_every_config(installed_wheel):
    in_wheel = {kind: yaml_names(installed_wheel / "mmpc" / "configs" / kind) for kind in KINDS}
    assert in_wheel == shipped_names()


def test_wheel_ships_the_trained_agents(installed_wheel):
    from mmpc.rl.runs import SHIPPED_MODELS, shipped_models

    assert shipped_models()
    for name in shipped_models():
        for part in ("model.zip", "config.yaml"):
            shipped = installed_wheel / "mmpc" / "rl" / "models" / name / part
            assert shipped.read_bytes() == (SHIPPED_MODELS / name / part).read_bytes()


def test_wheel_ships_the_trained_proposers(installed_wheel):
    from mmpc.imitation.proposer_driver import SHIPPED_PROPOSERS, shipped_proposers

    assert shipped_proposers() == ["cruise", "high_speed"]
    for name in shipped_proposers():
        shipped = installed_wheel / "mmpc" / "imitation" / "models" / f"{name}.pt"
        assert shipped.read_bytes() == (SHIPPED_PROPOSERS / f"{name}.pt").read_bytes()
        assert shipped.stat().st_size < 5 * 2**20


def test_wheel_ships_every_package_and_declares_the_drivers(installed_wheel):
    def modules(root: Path, package: str) -> set[str]:
        found = set()
        for init in root.rglob("__init__.py"):
            if "__pycache__" not in init.parts:
                found.add(".".join((package, *init.parent.relative_to(root).parts)))
        return found

    in_source = modules(REPO / "mmpc", "mmpc") | {"mmpc.rl", "mmpc.imitation", "mmpc.configs"}
    assert modules(installed_wheel / "mmpc", "mmpc") == in_source
    (entry_points,) = installed_wheel.glob("mmpc-*.dist-info/entry_points.txt")
    declared = entry_points.read_text()
    assert "[mmpc.drivers]" in declared and all(f"\n{name} = " in declared
                                                for name in ("mpc", "frenet", "standard-mpc", "batch-nlp", "bc", "sb3", "safe-random", "safe-expert"))


def test_installed_wheel_loads_shipped_configs_by_name(installed_wheel, tmp_path):
    script = textwrap.dedent(
        """
        import json, sys
        import mmpc
        from mmpc.configs import shipped_config_dir
        from mmpc.scenario import load_scenario, SCENARIO_DIR
        from mmpc.config import load_config
        from mmpc.rl.config import RLConfig
        assert mmpc.__file__.startswith(sys.argv[1]), mmpc.__file__
        assert str(shipped_config_dir("scenarios")).startswith(sys.argv[1]), shipped_config_dir("scenarios")
        loaded = {
            "scenarios": sorted(load_scenario(p.stem).name for p in SCENARIO_DIR.glob("*.yaml")),
            "rl": sorted(p.stem for p in shipped_config_dir("rl").glob("*.yaml") if load_config(RLConfig, p.stem)),
            "rl_default_scenario": RLConfig().scenario.name,
        }
        print(json.dumps(loaded))
        """
    )
    env = {**os.environ, "PYTHONPATH": str(installed_wheel)}
    run = subprocess.run(
        [sys.executable, "-c", script, str(installed_wheel)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stderr
    loaded = json.loads(run.stdout.strip().splitlines()[-1])
    assert loaded["scenarios"] == shipped_names()["scenarios"]
    assert loaded["rl"] == shipped_names()["rl"]
    assert loaded["rl_default_scenario"] == "rl_highway_fast"  # RLConfig's default scenario is a shipped file
