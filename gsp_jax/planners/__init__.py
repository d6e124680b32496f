"""Every planner by name, whichever folder it comes from (registry.py: `register`, `make`, `plan`, `decide`,
`check`), and one unseen episode planned online in one jitted call, Table 1's form (online.py)."""
