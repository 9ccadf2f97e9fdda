"""lca_sim.analysis."""
