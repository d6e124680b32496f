"""gsp_jax: grasp-sequence planning for in-hand tool manipulation, in pure JAX.

Data flows one way:

    models/*.xml -> hand.py (constant arrays) -> kinematics.py, ik.py, wrench.py (kernels)
    scenario.py (Episode) -> surrogate.py (reset/step, reward terms) -> dp.py (table, Bellman backup)
                                                                     -> policies.py (one `act(state)` interface)

The surrogate step is `surrogate.Surrogate.step`: `realise` (IK) at the current and next waypoint, then
`score` (three wrench solves) -> reward.
"""


def _import_mjx_quietly() -> None:
    """mujoco-mjx prints "Failed to import warp: ..." twice when it probes its optional NVIDIA Warp backend,
    which we do not use; import it once here with those two lines held back (anything else it prints passes)."""
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        import mujoco.mjx  # noqa: F401
    for line in buf.getvalue().splitlines():
        if not line.startswith(("Failed to import warp:", "Failed to import mujoco_warp:")):
            print(line)


_import_mjx_quietly()
