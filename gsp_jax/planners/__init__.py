"""Every planner by name, whichever folder it comes from (registry.py: `register`, `make`, `plan`, `decide`,
`check`), and one unseen episode planned online in one jitted call, Table 1's form (online.py)."""
from gsp_jax.planners.registry import Plan, Planner, check, decide, describe, make, names, plan, register, returns

__all__ = ["Plan", "Planner", "check", "decide", "describe", "make", "names", "plan", "register", "returns"]
