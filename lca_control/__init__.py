"""lca_control: the controllers of lca_hil (the paper's section 6 cascaded PI loops).

The discrete PI core and the cascade arrive with the ROS nodes; like lca_sim, this package stays
free of ROS, clocks and I/O.
"""
