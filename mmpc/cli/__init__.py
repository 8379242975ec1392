"""The command line: ``mmpc solve | drive | evaluate | rl ... | imitate ...`` (:mod:`~mmpc.cli.main`);
shared argument types in :mod:`~mmpc.cli.arguments`."""
