"""The reward's calibrated defaults, read by `surrogate.RewardConfig`. Written by `python -m experiments calibrate
--write` (2026-11-25); rerun it rather than editing by hand."""

CALIBRATED = dict(
    friction_scale=1.0,
    grip=4.0,
    grip_scales_with_mass=True,
    squeeze=0.0,
    motors=False,
    fall_unmet=0.3,
    w_wrench_change=5.0,
    change_falls=True,
)
MEASURED = dict(  # on the calibration episodes, against the physics check
    sets='train+val+stress-cal',
    backend='c',
    sequences=4149,
    spearman=0.387,  # rank correlation of surrogate return and -simulated angle error, pooled
    feasible_held=0.600,  # share of the surrogate-feasible sequences that held
    dp_opt_falls=32,  # of 84 episodes
    dp_opt_changes=2.57,  # mean grasp changes per episode of the DP-optimal plans
    best_spearman=0.551,  # the sweep's highest correlation (another candidate), and its
    best_spearman_se=0.024,  # bootstrap SE; see calibrate.choose_and_write for the choice
)
