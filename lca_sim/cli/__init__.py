"""lca_sim.cli: the console scripts (lca-sim, lca-hil, lca-plot), their result files and plots."""
