"""lca_sim.canbus."""
