"""lca_sim.config: YAML files -> validated, typed parameters (the one place that reads them)."""
