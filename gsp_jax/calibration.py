"""The reward's calibrated defaults, read by `surrogate.RewardConfig`. Written by `python -m experiments calibrate
--write`; rerun it rather than editing by hand. (Not yet calibrated: the paper's values.)"""

CALIBRATED = dict(
    friction_scale=1.0,
    fall_unmet=0.3,
    w_wrench_change=1.0,
    change_falls=True,
)
MEASURED = dict()
