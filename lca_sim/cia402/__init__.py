"""lca_sim.cia402.device."""
