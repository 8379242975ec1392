"""The YAML configs that ship with mmpc, installed as the package ``mmpc.configs``.

``scenarios/`` (:class:`mmpc.scenario.ScenarioConfig`) and ``rl/`` (:class:`mmpc.rl.config.RLConfig`):
recipes, read by name with :func:`mmpc.config.load_config` (a config class names its folder in
``config_folder``). Defaults are not restated here: they live in the dataclasses
(``mmpc config show KIND`` prints them). In a checkout (or an
editable install) this is the repository's ``configs/`` folder; in an installed wheel it is
``site-packages/mmpc/configs``. Code finds the files through :func:`shipped_config_dir`, never
through a path relative to the repository.
"""
from __future__ import annotations

from pathlib import Path

#: The sub-folders of shipped YAML files.
KINDS = ("rl", "scenarios")


def shipped_config_dir(kind: str) -> Path:
    """The folder of the shipped ``<name>.yaml`` files of one kind, e.g. ``"scenarios"``.

    Raises:
        ValueError: ``kind`` is not one of :data:`KINDS`.
    """
    if kind not in KINDS:
        raise ValueError(f"config kind {kind!r}: expected one of {list(KINDS)}")
    return Path(__file__).resolve().parent / kind
