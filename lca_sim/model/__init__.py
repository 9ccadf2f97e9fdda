"""lca_sim.model."""
