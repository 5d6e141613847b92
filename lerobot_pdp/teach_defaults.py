"""Defaults of teaching a new mode (:func:`lerobot_pdp.teaching.teach_new_mode`, ``lerobot-pdp teach``).

A module of their own so that the command line's parser shows them without importing torch and LeRobot. Chosen
on avoiding's zero-mode validation scene (docs/experiments.md, "Teaching a new mode where no latent reaches the
route").
"""

TEACH_STEPS = 3000
TEACH_LR = 1e-4
TEACH_DEMO_SHARE = 0.25
TEACH_BATCH_SIZE = 64
TEACH_LATENTS = ("encoder", "geometry")
TEACH_LATENT = "encoder"
