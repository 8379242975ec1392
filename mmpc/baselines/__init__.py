"""Baseline planners behind the driver interface (:mod:`mmpc.drivers`): a standard single-trajectory MPC and a batch of goal-directed NLPs (CasADi + IPOPT), and a Frenet-frame sampling planner."""
