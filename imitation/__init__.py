"""mmpc.imitation: expert demonstrations from the multi-modal MPC and imitation learning.

- :mod:`mmpc.imitation.rollout`: lockstep episodes recorded as arrays (kinematics
  observation, executed command, reward, episode end, the driver's diagnostics, the road-frame
  ego state and nearest vehicles).
- :mod:`mmpc.imitation.features`: the policy's road-frame inputs.
- :mod:`mmpc.imitation.dataset` / :mod:`mmpc.imitation.demos`: ``mmpc imitate demos``, resumable
  generation of a Minari dataset.
- :mod:`mmpc.imitation.policy`: the MLP policy, its checkpoint and the ``bc:PATH`` driver.
- :mod:`mmpc.imitation.bc` / :mod:`mmpc.imitation.dagger`: behaviour cloning and DAgger (a
  beta-mixture of expert and learner drives, the MPC labels the learner's states in large
  optimizer batches); :mod:`mmpc.imitation.dagger_rounds`: the rounds it shares with the mode
  proposer's DAgger (:mod:`mmpc.imitation.proposer_dagger`).
- :mod:`mmpc.imitation.compare` / :mod:`mmpc.imitation.bench`: closed-loop table and inference cost.
- :mod:`mmpc.imitation.export`: the policy as a stable-baselines3 policy (PPO can start from it).

Minari (``mmpc[datasets]``) is imported only where a dataset is written or read.
"""
