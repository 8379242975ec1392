"""mmpc.imitation: expert demonstrations and imitation learning from the MPC (planned)."""
