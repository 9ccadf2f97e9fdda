"""lca_sim.cli.sim."""
