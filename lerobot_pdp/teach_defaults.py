"""Defaults of teaching a new mode (:func:`lerobot_pdp.teaching.teach_new_mode`, ``lerobot-pdp teach``).

A module of their own so that the command line's parser shows them without importing torch and LeRobot. Chosen
on avoiding's zero-mode validation scene (docs/experiments.md, "Teaching a new mode where no latent reaches the
route").
"""

from .steer_requests import mode_key

TEACH_STEPS = 3000
TEACH_LR = 1e-4
TEACH_DEMO_SHARE = 0.25
TEACH_BATCH_SIZE = 64
TEACH_LATENTS = ("encoder", "geometry")
TEACH_LATENT = "encoder"


def check_teach_settings(steps: int, lr: float, demo_share: float, batch_size: int = TEACH_BATCH_SIZE) -> None:
    """Teaching's numbers, each refused with what it must be (here, so the command line checks them at once)."""
    errors = []
    if not isinstance(steps, int) or steps < 1:
        errors.append(f"steps must be a positive integer, got {steps!r}")
    if not lr > 0:
        errors.append(f"lr must be > 0, got {lr!r}")
    if not 0 < demo_share <= 1:
        errors.append(f"demo_share must be in (0, 1], got {demo_share!r}")
    if not isinstance(batch_size, int) or batch_size < 2:
        errors.append(f"batch_size must be an integer >= 2, got {batch_size!r}")
    if errors:
        raise ValueError("teach: " + "; ".join(errors))


def check_mode_name(name: str | None) -> None:
    """A new mode's name must not read as a mode id: ``--policy.steer_mode=3`` steers to mode id 3."""
    if name is not None and isinstance(mode_key(str(name)), int):
        raise ValueError(f"teach: mode name {name!r} reads as a mode id (--policy.steer_mode={str(name).strip()} "
                         "steers to the mode of that id); give a name with a letter in it")
