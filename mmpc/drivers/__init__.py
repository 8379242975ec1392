"""Drivers: the interface (:mod:`~mmpc.drivers.base`), the registry of driver specs
(:mod:`~mmpc.drivers.registry`), the multi-modal MPC driver and the baselines (Frenet sampling,
standard MPC and batch NLP on CasADi/IPOPT), which load on first use."""

from mmpc.drivers.base import Candidates, Decision, Driver, Observation
from mmpc.drivers.mpc_driver import MPCDriver
from mmpc.drivers.registry import check_spec, driver_files, driver_names, make_driver, register_driver

__all__ = [
    "Candidates", "Decision", "Driver", "MPCDriver", "Observation", "check_spec", "driver_files", "driver_names",
    "make_driver", "register_driver",
]
