"""The solvers the surrogate step is built from: collision-avoiding IK (ik.py, vmapped; ik_lanes.py, batch-last
on a CPU) and contact forces in friction cones with the feasibility LPs (wrench.py)."""
