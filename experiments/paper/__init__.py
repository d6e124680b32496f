"""The paper's figures and table, and the runs behind them (DP, PPO training)."""
