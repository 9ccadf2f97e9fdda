"""lca_sim.analysis: linearisation, identification, the paper's figures as data (pure)."""
