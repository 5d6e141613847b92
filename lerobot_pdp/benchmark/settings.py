"""What the benchmark runs: per-env training budgets, the methods and ablations, and the run config.

Hyperparameters are per env, identical for all scenes and all methods where they apply.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..envs.suite import SuiteEnv

SCENES = (0, 1, 2, 3)  # the test split: scene 0 and the test scenes 1-3, evaluated once with frozen settings

# The validation split: scene 0 plus shipped validation scenes (``scenes/<scene_key>_val<k>.json``), of the
# same families as scenes 1-3 (one training mode left open; none open, with the scene's own way-points) but
# other geometry: other open modes, and new routes that leave the training modes elsewhere than scene 3's
# (another window row / side / stage, beyond wide instead of diagonal). Every setting is chosen on these
# scenes and VALIDATION_SEEDS, so that the test scenes and seeds stay unseen until the frozen run.
VALIDATION_SCENES: dict[str, tuple[str, ...]] = {
    "reach-around": ("val1", "val2", "val3", "val4"),
    "avoiding": ("val1", "val2", "val3", "val4", "val5"),
    "pick-place": ("val1", "val2", "val3", "val4", "val5", "val6", "val7"),
    "kitchen-microwave": ("val1", "val2", "val3"),  # one zero-mode scene so far: the arm sweeps a large volume
}
SPLITS = ("test", "validation")
SPACINGS = ("leading", "trailing", "even")  # DDIM grids of the shared sampler (TrainSettings.timestep_spacing)
TEST_SEEDS = (0, 1, 2)  # the development seeds so far; fresh test seeds come from range(VALIDATION_SEED_MIN)
VALIDATION_SEEDS = (100, 101, 102)
VALIDATION_SEED_MIN = 100  # seeds >= this are validation seeds and never reported as test numbers


# Scenes of each split where no adaptation of the trained PDP reaches the route: where `benchmark --teach` teaches
# the demonstration as a new mode. Checked on the validation checkpoint: the fit with chunk noises stays at 0 %,
# and avoiding's grid of latents too; pick-place val4 is nearly, not strictly, out of every latent's reach (a z
# search scored by way-points found one at 10 %). Avoiding val5's chunk noises replay the turn in part (57.5 %).
# Pick-place's val5 / val6 and a first draft of its test scene are no teaching scenes: no latent reaches them but
# the chunk noises do (100 %). The noises can replay a route 0.40 m out up to 5 cm narrower than demonstrated
# (val4 clips its window by 0.7 cm; val6 is replayed within 0.2 cm), so pick-place's test scene 4 sets its window
# 0.51 m off B (z search 0 of 512 rollouts, z + noises 0 %), and so does val7, at the reach stage (the same checks,
# 0 %; added after PDP's and BC's settings were frozen). Test scene 4 is outside SCENES: only `--teach --split test`
# evaluates it, once, with TEACH_FROZEN.
TEACH_SCENES: dict[str, dict[str, tuple[int | str, ...]]] = {
    "avoiding": {"validation": ("val4", "val5"), "test": (4,)},
    "pick-place": {"validation": ("val4", "val7"), "test": (4,)},
}


# What --teach chose per method on the validation split (benchmark/teaching.py: the best new route among the
# settings that keep scene 0 within 5 points), frozen before a test run, per (env, budget), and the record.
# Avoiding, seed 100, val4 (docs/results/avoiding/teach/): PDP 90 % on the new route at 3000 steps, scene 0 kept;
# BC 100 % at 1000 steps (it never held scene 0); DP at most 17.5 %, no setting keeping its scene 0.
# Pick-place, seed 100, val4 (docs/results/pick-place/teach/): PDP 85 % at 3000 steps, scene 0 kept (100 %); BC 0 %
# at every setting (ties go to the first, 300 steps); DP 17.5 % at 3000 steps, 1e-4 (20 % at 1e-3 dropped scene 0
# by 9 points), frozen after PDP's and BC's.
TEACH_FROZEN: dict[tuple[str, str], dict[str, dict[str, Any]]] = {
    ("avoiding", "full"): {"pdp": {"steps": 3000, "lr": 1e-4}, "bc": {"steps": 1000, "lr": 1e-4},
                           "dp": {"steps": 3000, "lr": 1e-3}},
    ("pick-place", "full"): {"pdp": {"steps": 3000, "lr": 1e-4}, "bc": {"steps": 300, "lr": 1e-4},
                             "dp": {"steps": 3000, "lr": 1e-4}},
}
TEACH_RECORDS: dict[tuple[str, str], tuple[str, ...]] = {
    ("avoiding", "full"): ("docs/results/avoiding/teach/teach_pdp.json", "docs/results/avoiding/teach/teach_bc_dp.json"),
    ("pick-place", "full"): ("docs/results/pick-place/teach/teach_pdp.json", "docs/results/pick-place/teach/teach_bc_dp.json"),
}


def teach_scenes(env: str, split: str, evaluated: tuple[int | str, ...] | None = None) -> tuple[int | str, ...]:
    """The zero-mode scenes of ``split`` on ``env`` that ``--teach`` teaches: those among ``evaluated`` (the run's
    ``--scenes``) when given. An error if there are none."""
    scenes = TEACH_SCENES.get(env, {}).get(split, ())
    if not scenes:
        have = {e: sorted(s) for e, s in TEACH_SCENES.items()}
        raise ValueError(f"--teach: {env} has no zero-mode scene in the {split} split; envs and splits with one: {have}")
    if evaluated is not None:
        picked = tuple(s for s in scenes if s in evaluated)
        if not picked:
            raise ValueError(f"--teach teaches {env}'s zero-mode scenes of the {split} split, {list(scenes)}: "
                             "evaluate at least one of them too (--scenes)")
        scenes = picked
    return scenes


def split_scenes(env: str, split: str = "test") -> tuple[int | str, ...]:
    """Scenes ``split`` evaluates on ``env`` (a suite name): scene 0 always, then the test scenes 1-3 or the
    env's validation scenes."""
    if split == "test":
        return SCENES
    if split != "validation":
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    if env not in VALIDATION_SCENES:
        raise ValueError(f"{env} ships no validation scenes yet; envs with them: {sorted(VALIDATION_SCENES)}")
    return (0, *VALIDATION_SCENES[env])


def split_seeds(split: str = "test", quick: bool = False) -> list[int]:
    """Default training seeds of ``split`` (the first one only with ``quick``)."""
    seeds = list(VALIDATION_SEEDS if split == "validation" else TEST_SEEDS)
    return seeds[:1] if quick else seeds


def check_split(split: str, scenes: tuple[int | str, ...], seeds: list[int], flag: bool = True) -> None:
    """Refuse a run that mixes the splits: test scenes or test seeds in a validation run, validation scenes
    or seeds in a test run (numbers from either would then no longer mean what their split says). ``flag``: the
    command has ``--split`` (else the scene decides the split, and the message says so)."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    val_scenes = [s for s in scenes if isinstance(s, str)]
    test_scenes = [s for s in scenes if not isinstance(s, str) and s != 0]
    val_seeds = [s for s in seeds if s >= VALIDATION_SEED_MIN]
    test_seeds = [s for s in seeds if s < VALIDATION_SEED_MIN]
    mixed = {"validation": (test_scenes, test_seeds), "test": (val_scenes, val_seeds)}[split]
    if not any(mixed):
        return
    other = "test" if split == "validation" else "validation"
    got = "; ".join(f"{other} {what} {', '.join(map(str, xs))}" for what, xs in zip(("scene(s)", "seed(s)"), mixed,
                                                                                  strict=True) if xs)
    rule = (f"validation scenes (val1, val2, ...) go with seeds >= {VALIDATION_SEED_MIN}, test scenes (1, 2, ...) "
            f"with seeds below")
    raise ValueError(f"--split {split} got {got}: {rule}" if flag else
                     f"{split} scene {', '.join(map(str, scenes))} got {got}: {rule}")


def scene_label(scene: int | str) -> str:
    """Folder / results key of a scene: ``scene1`` for test scene 1, ``scene_val1`` for validation scene val1
    (the ``scene`` prefix keeps every per-scene key of results.json recognisable)."""
    return f"scene_{scene}" if isinstance(scene, str) else f"scene{int(scene)}"


def scene_seed_offset(scene: int | str) -> int:
    """Offset of a scene in the rollout and demonstration seeds: k for scene k, 100 + k for val<k>, so that
    no two scenes share rollout seeds."""
    return 100 + int(scene[3:]) if isinstance(scene, str) else int(scene)


@dataclass(frozen=True)
class TrainSettings:
    """Training budget and sampler shared by every method on one env (fairness: same data, steps, batch,
    lr, DDIM steps)."""

    steps: int
    batch_size: int = 64
    lr: float = 1e-3
    episodes_per_mode: int = 10
    warmup_steps: int = 100
    # Training windows dropped at each episode's end (None = each policy's default, LeRobot's 7). An env
    # whose last action matters (pick-place's release) needs windows that execute it right away.
    drop_n_last_frames: int | None = None
    # DDIM steps of PDP and DP, written into their checkpoints (lerobot-eval then samples the same way)
    # and used when evaluating. The whole K = 20 chain: grasps need it (docs/experiments.md, "DDIM steps").
    inference_steps: int = 20
    # Grid of those steps, one sampler for PDP and DP: diffusers' DDIM as LeRobot's diffusion steps it,
    # "leading" (LeRobot's default) or "trailing" (starts from pure noise below K steps). At K = 20 steps
    # both visit every step. "even" = PDP's own sampler (not available to DP).
    timestep_spacing: str = "leading"


# Per env: (full, quick). The paper's lr 1e-4 needs far more steps than a CPU budget allows; 1e-3 with a
# cosine schedule converges in a few thousand steps for every method here (and steers better on
# reach-around's validation scenes, which made it PDPConfig's default). Quick settings sample with 5
# DDIM steps: DP's noise adaptation backpropagates through every step (~4x longer at 20), which would
# push `make demo` past its time budget. Pick-place trains twice as long as the others: at 8000 steps its
# diffusion loss was still falling and releases landed off target (every method gets the same budget).
# These were chosen on the development scenes (docs/experiments.md has the numbers behind each choice);
# pick-place's 16000 steps were kept on its validation split against 8000 (validation_steps.json there).
_QUICK_SAMPLER = 5


SETTINGS: dict[str, tuple[TrainSettings, TrainSettings]] = {
    "reach-around": (TrainSettings(steps=6000),
                     TrainSettings(steps=1500, episodes_per_mode=10, inference_steps=_QUICK_SAMPLER)),
    "avoiding": (TrainSettings(steps=8000),
                 TrainSettings(steps=2000, episodes_per_mode=5, inference_steps=_QUICK_SAMPLER)),
    "pick-place": (TrainSettings(steps=16000, episodes_per_mode=3, drop_n_last_frames=0),
                   TrainSettings(steps=2000, episodes_per_mode=1, drop_n_last_frames=0,
                                 inference_steps=_QUICK_SAMPLER)),
    "kitchen-microwave": (TrainSettings(steps=6000),
                          TrainSettings(steps=1500, episodes_per_mode=5, inference_steps=_QUICK_SAMPLER)),
}


# The form of PDP's z -> (gamma, beta) map, a training setting (``benchmark --film`` trains another one, e.g.
# to compare both on the validation split): "mlp" is the paper's [16, 32] MLP (PDPConfig's default),
# "affine" one linear layer. FILM names each env's form where it is not the paper's. Pick-place's affine map
# (a latent between two carry modes mixes their modulations; scene 3's window lies between them) was adopted
# on its development scenes and kept on its validation split against the MLP, within a standard error
# (docs/results/pick-place/validation_film.json). Fitting
# settings (steps, lr, the |z|^2 weight) are not training flags: they are chosen per env in FROZEN.
FILM_FORMS: dict[str, tuple[str, ...]] = {"mlp": (), "affine": ("--policy.film_hidden_dims=[]",)}
FILM: dict[str, str] = {"pick-place": "affine"}
# How PDP's L_rec reduces a trace's squared error, a training setting like FILM (``benchmark --rec-reduction``):
# "mean" over its elements (PDPConfig's default, every env), or the paper's "sum".
REC_REDUCTIONS: dict[str, tuple[str, ...]] = {"mean": (), "sum": ("--policy.embed_rec_reduction=sum",)}


# What the validation split chose per method (``benchmark --split validation --validate``, validation.py),
# frozen here before a test run, per (env, budget) (:func:`budget_key`: "full" | "quick", "+images" for the
# camera variant, whose choices are made on its own validation runs): {"sampler": [DDIM steps, grid],
# "adapt": keyword arguments of ``evaluation.adapt`` (steps, lr; PDP lam / objective, DP per_chunk)}, the
# shape of validation.json's "chosen". A missing entry means the env's TrainSettings sampler and each
# method's default adaptation. VALIDATION_RECORDS names the committed validation.json of each budget; both
# are recorded in results.json.
FROZEN: dict[tuple[str, str], dict[str, dict[str, Any]]] = {
    # seed 100, 20 rollouts per scene, scene 0 + val1-4 (docs/results/reach-around/validation_quick.md); PDP
    # fits one sampler noise per chunk after z (100 % on val1-4; validated anew on a retrained run that did
    # not reproduce the earlier record, whose choice was the fit with lam 0)
    ("reach-around", "quick"): {"pdp": {"sampler": [10, "trailing"], "adapt": {"noise": "chunks"}},
                                "dp": {"sampler": [5, "trailing"]}},
    # seed 100, 40 rollouts, scene 0 + val1-4 (docs/results/reach-around/validation.md)
    ("reach-around", "full"): {"pdp": {"adapt": {"objective": "sample"}},
                               "dp": {"sampler": [5, "trailing"]},
                               "bc": {"adapt": {"lr": 1e-3}}},
    # seed 100, 40 rollouts, scene 0 + val1-3; DP kept its defaults; PDP fits one sampler noise per chunk after
    # z (100 % on val1-3 against 64.2 % for the z fit alone; chosen when that candidate joined the list, the
    # other rows reused from the earlier record after the retrained run reproduced it)
    ("kitchen-microwave", "full"): {"pdp": {"adapt": {"noise": "chunks"}}, "bc": {"adapt": {"lr": 1e-4}}},
    # seed 100, 40 rollouts, scene 0 + val1-4 (docs/results/avoiding/validation.md): PDP fits one sampler noise
    # per chunk after z (75.0 % against 59.4 % for the encoder's latent alone, the choice before that candidate
    # joined; val4 stays 0 %); DP kept its defaults; the MLP FiLM was kept against the affine one
    # (docs/results/avoiding/validation_film.json)
    ("avoiding", "full"): {"pdp": {"adapt": {"noise": "chunks"}},
                           "bc": {"adapt": {"steps": 300, "lr": 1e-3}}},
    # seed 100, 40 rollouts, scene 0 + val1-4 (docs/results/pick-place/validation.md): PDP fits one sampler
    # noise per chunk after z (75.0 % against 48.1 % for the default fit: val3 0 -> 100 %, val4 stays 0 %;
    # validated anew: the retrained run did not reproduce the earlier record, whose choice was the default fit),
    # with the affine FiLM and 16000 steps (validation_film.json, validation_steps.json); DP one noise per
    # executed chunk (the only candidate above 0 % on a validation scene); BC 300 fine-tuning steps at 1e-4
    ("pick-place", "full"): {"pdp": {"adapt": {"noise": "chunks"}},
                             "dp": {"adapt": {"per_chunk": True}},
                             "bc": {"adapt": {"steps": 300, "lr": 1e-4}}},
    # camera variant, seed 100, 20 rollouts, scene 0 + val1-4 (docs/results/reach-around/validation_camera_quick.md):
    # VQ-BeT fine-tunes 300 steps at lr 1e-4 (its default, 100 at 1e-5, moved nothing: 0 %); PDP and DP sample
    # with 5 "trailing" DDIM steps, DP adapts one noise per executed chunk (96.2 % on val1-4 against 0 % for its
    # default), PDP one sampler noise per chunk after z (100 % against 43.8 % for the default fit; chosen when
    # that candidate joined the list, the other rows reused after the retrained run reproduced the record).
    ("reach-around", "quick+images"): {"vqbet": {"adapt": {"steps": 300, "lr": 1e-4}},
                                       "pdp": {"sampler": [5, "trailing"], "adapt": {"noise": "chunks"}},
                                       "dp": {"sampler": [5, "trailing"], "adapt": {"per_chunk": True}}},
}
VALIDATION_RECORDS: dict[tuple[str, str], str] = {
    ("reach-around", "quick"): "docs/results/reach-around/validation_quick.json",
    ("reach-around", "full"): "docs/results/reach-around/validation.json",
    ("kitchen-microwave", "full"): "docs/results/kitchen-microwave/validation.json",
    ("avoiding", "full"): "docs/results/avoiding/validation.json",
    ("pick-place", "full"): "docs/results/pick-place/validation.json",
    ("reach-around", "quick+images"): "docs/results/reach-around/validation_camera_quick.json",
}


def budget_key(quick: bool, obs: str = "state") -> str:
    """The budget part of a FROZEN / VALIDATION_RECORDS key: "full" or "quick", with "+images" for the camera
    variant (choices made on state observations are not carried over to it, nor back)."""
    return ("quick" if quick else "full") + ("" if obs == "state" else f"+{obs}")


def frozen_for(env: str, quick: bool, method: str, obs: str = "state") -> dict[str, Any]:
    """The frozen choice of ``method`` on ``env`` at the full or quick budget, state or camera variant ({} if
    none). An ablation is PDP with one part changed, so it samples and fits with PDP's choice (ablations are
    not validated on their own)."""
    chosen = FROZEN.get((env, budget_key(quick, obs)), {})
    return chosen.get(method, chosen.get("pdp", {}) if method in ABLATIONS else {})


# The camera variant (``benchmark --obs images``). One camera per env, chosen so that the agent, the goal and
# every scene's barriers are in view (reach-around's top view shows scene 3's wall edge-on, hiding its
# window; the oblique view shows the window), at a size a 2-core CPU trains at the quick budget in under an
# hour (docs/results/cameras.md).
CAMERAS = {"reach-around": "oblique", "avoiding": "top", "pick-place": "oblique"}
IMAGE_SIZE = 64
# The vision encoder of every camera method, identical for PDP and DP (LeRobot's diffusion image encoder):
# ResNet-18 without pretrained weights (LeRobot DP's default ImageNet weights would be downloaded at start-up,
# which fails offline), GroupNorm, 32 spatial-softmax keypoints, no crop (both policies' defaults).
VISION_FLAGS = ("--policy.vision_backbone=resnet18", "--policy.pretrained_backbone_weights=null",
                "--policy.use_group_norm=true", "--policy.spatial_softmax_num_keypoints=32",
                "--policy.use_separate_rgb_encoder_per_camera=false")
# LeRobot's VQ-BeT, the third camera method (``vqbet`` takes exactly one camera and no environment state):
# the same vision encoder as PDP and DP (its 84x84 crop off: the images are IMAGE_SIZE) and the same two
# observation frames (its default is 5: 2.5x the ResNet passes per step), LeRobot's own action tokens (3
# tokens of 5 actions, 5 executed per query) and GPT. Its residual VQ-VAE trains on the actions for the first
# VQBET_VQVAE_SHARE of the steps (``train_args``): LeRobot's default of 20000 exceeds the whole CPU budget.
VQBET_FLAGS = (*(f for f in VISION_FLAGS if not f.startswith("--policy.use_separate_rgb_encoder")),  # one camera
               "--policy.crop_shape=null", "--policy.n_obs_steps=2")
VQBET_VQVAE_SHARE = 0.2


@dataclass(frozen=True)
class Method:
    """How one method is trained (LeRobot policy type + CLI overrides) and adapted to a new scene."""

    name: str
    policy_type: str
    overrides: tuple[str, ...] = ()
    adapt: str = "fit_latent"  # fit_latent | noise | finetune
    steerable: bool = True  # conditions scene-0 rollouts on each mode's mean latent


def film_form(env: str, film: str | None = None) -> str:
    """PDP's FiLM form on ``env``: ``film`` if given, else the env's (:data:`FILM`, the paper's MLP by default)."""
    form = film or FILM.get(env, "mlp")
    if form not in FILM_FORMS:
        raise ValueError(f"film must be one of {sorted(FILM_FORMS)}, got {form!r}")
    return form


def methods_for(suite: SuiteEnv, film: str | None = None, rec_reduction: str = "mean") -> dict[str, Method]:
    """Main methods and ablations for ``suite`` (PDP's trace dims and gripper segmentation come from it).

    ``film`` trains PDP and its ablations with that FiLM form instead of the env's (:func:`film_form`),
    ``rec_reduction`` with that L_rec reduction (:data:`REC_REDUCTIONS`). For a
    camera variant of an env (``suite.camera_kwargs``) only the methods that take images, each with the same
    :data:`VISION_FLAGS`."""
    try:
        from ..configuration_pdp import PDPConfig
        from .baselines import dp_config_matching

        dp = tuple(dp_config_matching(PDPConfig(device="cpu")))  # DP mirrors PDP's backbone and sampler
    except ImportError:  # baselines not importable: DP is unavailable, PDP still runs
        dp = ()
    pdp = [f"--policy.trace_dims=[{','.join(map(str, suite.trace_dims))}]"]
    if suite.segment_on_gripper is not None:
        pdp += [f"--policy.segment_gripper_dim={suite.segment_on_gripper}", "--policy.trace_normalize=endpoints"]
    if rec_reduction not in REC_REDUCTIONS:
        raise ValueError(f"rec_reduction must be one of {sorted(REC_REDUCTIONS)}, got {rec_reduction!r}")
    pdp = (*pdp, *FILM_FORMS[film_form(suite.name, film)], *REC_REDUCTIONS[rec_reduction])
    if suite.camera_kwargs:
        # VQ-BeT adapts like BC, by fine-tuning its weights (LeRobot's vqbet has no goal input for the
        # paper's way-point goals); its discrete codes are sampled, not steered
        return {"pdp": Method("pdp", "pdp", (*pdp, *VISION_FLAGS)),
                "dp": Method("dp", "diffusion", (*dp, *VISION_FLAGS), adapt="noise", steerable=False),
                "vqbet": Method("vqbet", "vqbet", VQBET_FLAGS, adapt="finetune", steerable=False)}
    return {
        "pdp": Method("pdp", "pdp", pdp),
        "dp": Method("dp", "diffusion", dp, adapt="noise", steerable=False),
        "bc": Method("bc", "mlp_bc", (), adapt="finetune", steerable=False),
        # ablations (paper Tables 3-5)
        "pdp_unaligned": Method("pdp_unaligned", "pdp", pdp + ("--policy.beta_geo=0",)),
        "pdp_onehot": Method("pdp_onehot", "pdp", pdp + ("--policy.latent_type=onehot",)),
        "pdp_concat": Method("pdp_concat", "pdp", pdp + ("--policy.latent_conditioning=concat",)),
        "pdp_input": Method("pdp_input", "pdp", pdp + ("--policy.latent_conditioning=input",)),
        "pdp_uncond": Method("pdp_uncond", "pdp", pdp + ("--policy.latent_conditioning=none",), steerable=False),
    }


ABLATIONS = ("pdp_unaligned", "pdp_onehot", "pdp_concat", "pdp_input", "pdp_uncond")


INIT_STEPS = (0, 10, 100)


@dataclass
class BenchmarkConfig:
    env: str
    out: Path
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    rollouts: int = 40
    methods: list[str] = field(default_factory=lambda: ["pdp", "dp", "bc"])
    quick: bool = False
    ablations: bool = False
    scenes: tuple[int | str, ...] = SCENES  # ints: test scenes; "val<k>": validation scenes (see split_scenes)
    split: str = "test"  # "test" or "validation": recorded in results.json, checked by check_split
    steps: int | None = None  # override the env's training steps (tests)
    episodes_per_mode: int | None = None  # override the env's dataset size (tests)
    lr: float | None = None  # override the env's learning rate, every method alike (choosing defaults)
    batch_size: int | None = None  # override the env's batch size, every method alike
    figures: bool = True
    # DDIM steps when evaluating PDP and DP (None: the env's TrainSettings.inference_steps). Sampling
    # only: cached evaluations made with other steps are redone on the same checkpoints.
    inference_steps: int | None = None
    # Their DDIM grid (None: the env's TrainSettings.timestep_spacing); likewise sampling only.
    timestep_spacing: str | None = None
    # With split="validation": also evaluate the candidate settings of validation.py and write
    # validation.json / validation.md (what each method would freeze for the test run).
    validate: bool = False
    # Where every method trains, adapts and acts ("cpu", "cuda", "cuda:1", ...). Not a training setting:
    # a run trained on one device is reused on another.
    device: str = "cpu"
    # PDP's FiLM form ("mlp" | "affine"; None: the env's, settings.FILM): a training setting, so that forms
    # can be compared on the validation split
    film: str | None = None
    # PDP's L_rec reduction ("mean" | "sum", REC_REDUCTIONS): a training setting like film
    rec_reduction: str = "mean"
    # "state" (default) or "images": the camera variant (CAMERAS[env] at IMAGE_SIZE, or camera / image_size)
    obs: str = "state"
    camera: str | None = None
    image_size: int = IMAGE_SIZE
    # Processes that evaluate validation candidates side by side (``--validate``); 1 = one after another.
    # Candidates are independent rollouts with their own cache files, so a machine with many cores (or a
    # GPU) runs a stage in the time of its slowest candidate.
    jobs: int = 1
    # With validate: an earlier validation.json whose candidate rows stand for this run's checkpoints where
    # they are checked identical, so that only candidates it lacks are evaluated (validation.check_reuse)
    reuse_validation: Path | None = None
    # Also teach every method the route of each zero-mode scene of the split (TEACH_SCENES) and measure the new
    # route and what scene 0 kept (benchmark/teaching.py): all candidates on the validation split, the frozen
    # choice (TEACH_FROZEN) on the test split
    teach: bool = False

    def observation(self) -> dict[str, Any] | None:
        """What the policies observe, as results.json and validation.json record it (``observation``): None for
        the state variant, which files made before the camera variant are too. ``camera`` must be resolved."""
        if self.obs == "state":
            return None
        return {"obs": self.obs, "camera": self.camera, "image_size": self.image_size}
