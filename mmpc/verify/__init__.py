"""Legal safety: verify that every step keeps a way out, whatever the other cars may legally do.

- :class:`TrafficAssumptions`: what the other cars may do, written once (:mod:`mmpc.verify.assumptions`);
- :func:`occupancy`: the road space each car may cover, as boxes per time interval;
- :class:`FailSafes`: braking manoeuvres to a lane centre, tried from every state;
- :class:`Verifier`: a command is verified when a fail-safe from its end meets no set;
- :class:`Guard`: per environment, the first of a list of commands that verifies, else the fail-safe stored;
- :class:`AssumptionMonitor`: which cars left the set predicted for them.

The layer sits above the simulator (the ego's command path is :mod:`mmpc.sim`'s) and below the drivers.
"""

from mmpc.verify.assumptions import TrafficAssumptions
from mmpc.verify.failsafe import FailSafes
from mmpc.verify.guard import Guard, Guarded
from mmpc.verify.monitor import AssumptionMonitor
from mmpc.verify.occupancy import Occupancy, counted_lanes, occupancy
from mmpc.verify.verifier import Verdict, Verifier

__all__ = ["AssumptionMonitor", "FailSafes", "Guard", "Guarded", "Occupancy", "TrafficAssumptions", "Verdict", "Verifier", "counted_lanes", "occupancy"]
