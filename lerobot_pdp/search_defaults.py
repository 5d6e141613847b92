"""Defaults of searching the latent space by outcome (:func:`lerobot_pdp.latent_search.search_latent`,
``lerobot-pdp search`` / ``search-curves``).

A module of its own so that the command line's parser shows them without importing torch.
"""

# rollouts in all before a candidate replaces the best (0: none; chosen on validation: docs/experiments.md,
# "Confirming the search's best")
CONFIRM_ROLLOUTS = 6
# a way-point counts as passed within this distance (metres), unless a radius is given (``--radius``)
WAYPOINT_RADIUS = 0.05
