"""Per-env method definitions of the benchmark: what each method's lerobot-train call gets."""

import draccus

from lerobot_pdp import PDPConfig
from lerobot_pdp.benchmark.protocol import methods_for
from lerobot_pdp.envs import get_suite_env


def _pdp_config(overrides: tuple[str, ...]) -> PDPConfig:
    """Parse ``--policy.*`` overrides the way lerobot-train does for ``--policy.type=pdp``."""
    return draccus.parse(PDPConfig, args=["--" + a.removeprefix("--policy.") for a in overrides] + ["--device=cpu"])


def test_pick_place_pdp_uses_an_affine_film_and_an_unpenalised_fit_every_other_env_the_defaults():
    pick = methods_for(get_suite_env("pick-place"))
    for name in ("pdp", "pdp_unaligned", "pdp_onehot"):  # the ablations vary one thing of the env's PDP
        cfg = _pdp_config(pick[name].overrides)
        assert tuple(cfg.film_hidden_dims) == () and cfg.segment_gripper_dim == 3 and cfg.fit_lambda == 0
    assert not any("film_hidden_dims" in a for m in ("dp", "bc") for a in pick[m].overrides)
    for env in ("reach-around", "avoiding", "kitchen-microwave"):
        cfg = _pdp_config(methods_for(get_suite_env(env))["pdp"].overrides)
        assert tuple(cfg.film_hidden_dims) == (16, 32) and cfg.segment_gripper_dim is None
        assert cfg.fit_lambda == PDPConfig.fit_lambda > 0
