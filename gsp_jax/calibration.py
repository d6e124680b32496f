"""The reward's calibrated defaults, read by `surrogate.RewardConfig`. Written by `python -m experiments calibrate
--write` (2026-11-23); rerun it rather than editing by hand."""

CALIBRATED = dict(
    friction_scale=1.0,
    grip=4.0,
    grip_scales_with_mass=True,
    fall_unmet=0.3,
    w_wrench_change=5.0,
    change_falls=True,
)
MEASURED = dict(  # on the calibration episodes, against the physics check
    sets='train+val',
    backend='c',
    sequences=1007,
    spearman=0.535,  # rank correlation of surrogate return and -simulated angle error, pooled
    feasible_held=0.880,  # share of the surrogate-feasible sequences that held
    dp_opt_falls=1,  # of 24 episodes
    dp_opt_changes=2.54,  # mean grasp changes per episode of the DP-optimal plans
    best_spearman=0.579,  # the sweep's highest correlation (another candidate), and its
    best_spearman_se=0.031,  # bootstrap SE; the winner falls least under DP optimal
)
