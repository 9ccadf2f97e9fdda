"""lca_control: the controllers of lca_hil (the paper's section 6 cascaded PI loops).

The discrete PI core, the velocity -> current cascade, the reference profiles, the section 6
tuning rule, the typed parameter tables and the plant contract (the topics, units and keys a
controller needs of a plant; every backend fills it). The bottom layer: it imports nothing from
lca_sim, and like lca_sim's core it stays free of ROS, clocks and I/O; the controller node is
a shell in `lca_sim.ros`. `import lca_control` loads nothing heavy.
"""
