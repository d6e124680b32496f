"""Planning over the surrogate: the DP table and Bellman backup (dp.py), Algorithm 2's lookahead (lookahead.py),
one policy interface (policies.py), the context a batch of episodes is planned from (evaluation.py)."""
