"""lca_sim.config.loader."""
