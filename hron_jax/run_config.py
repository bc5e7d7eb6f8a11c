"""The run config: one typed tree per training run (env, network, ppo), built and checked in one place.

    config = make_config('exploratory', 'rgbd_sg_attn', {'ppo.lr': 1e-4, 'env.camera.width': 128})
    config.env        NavConfig (directed / exploratory) or ChoiceConfig, task-dependent fields set
    config.network    ModelConfig with the variant's fields applied (models.VARIANTS[config.model])
    config.ppo        PPOConfig
    config.to_dict()  nested dict (config.json); TrainConfig.from_dict(d) rebuilds and re-checks it
    override(config, {'ppo.total_timesteps': ...})  the same config with dotted fields replaced

Every field has a dotted path: 'seed', 'ppo.num_envs', 'env.camera.width', 'network.hidden'.
`make_config` is the only way a TrainConfig is built (from_dict and override go through it): it
starts from the task's defaults (TASK_DEFAULTS), applies the overrides (strings are parsed in the
field's type), checks every value against RANGES and the generic rules (integers of the network
>= 1, floats finite), builds the typed configs (whose own __post_init__ checks cross-field rules,
e.g. minibatches dividing the rollout), and sets the fields that follow from other choices
(DERIVED: an override may only repeat their value). Every failure is a ConfigError naming the
dotted field, which the CLI turns into the option it came from.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any

from hron_jax.envs import DEFAULT_SCENES, TASKS, env_config
from hron_jax.errors import ConfigError
from hron_jax.labels import paper_label
from hron_jax.models.config import VARIANTS, ModelConfig
from hron_jax.paths import portable_path, resolve
from hron_jax.ppo import PPOConfig

# ------------------------------------------------------------------------------------------------
# Defaults per task (the one place they live).
#
# The paper (RLlib PPO, 8 envs, ~1.5 M steps): rollout 4096 steps, minibatch 128, 30 epochs,
# lr 1e-4, gamma 0.99, GAE lambda 0.9. We keep its rollout size (num_envs x num_steps = 64 x 64 =
# 4096 at the default --num-envs 64), minibatch size (32 minibatches -> 128), gamma, lambda and the
# 1.5 M steps, but run 4 epochs with lr 2.5e-4. Why: the update dominates training on CPU. Measured
# with `python -m hron_jax.bench train` (exploratory, rgbd_sg_attn, 2 shared EPYC cores): with 4
# epochs the update is already ~90 % of the time (each epoch costs ~2.3x the rollout: env step +
# policy forward), so 30 epochs would cut train steps/s ~7x, while with 64 parallel envs fresh,
# less correlated data is cheap; 4 epochs with a larger step is the usual trade (PureJaxRL / Brax
# defaults). Its policy steps are large: over the 1.5 M-step seed-0 runs (2026-12-04 to 06),
# median approx_kl per update 0.03 (directed, main model) and 0.04-0.055 (exploratory: main
# model, GCN, RGB-D only), clipped fraction 0.12 / 0.36-0.39 at clip 0.2; those runs learned
# steadily (README, Tables II and III). A target-KL stop was not tried. num_steps = 64 with
# 500-step episodes: GAE bootstraps across rollout ends from the value, which lambda = 0.9
# discounts anyway ((0.99*0.9)^64 ~ 6e-4).
# The choice task is a one-step bandit: rollouts of 4 steps are 4 independent episodes per env,
# gamma / lambda do not matter. Its lr is the paper's 1e-4 (2026-12-03, main model with
# distractors, HGT hidden 32, 61,440 env steps): at 3e-4 the policy turned deterministic within
# ~10-30 k env steps, often before it had solved the task, and 3 of 6 seeds froze at SR 0.75 (one
# more reached 1.0 and fell back to it): wrong with probability ~1 in exactly one of the four
# (goal, layout) cases, where the saturated softmax gets no gradient. At 1e-4, 9 of 9 seeds reached
# 1.0 between ~20 and ~55 k env steps and stayed there up to 61,440. RLlib's adaptive KL penalty
# (the paper preset's) did not help at 3e-4: its coefficient halves after each update whose KL is
# below target / 2, which took it from 0.2 to ~0 within the first ~20 updates. Trained on to the
# 200,000 here, solved seeds can lose it again (2026-12-07, SG without distractors, 8 seeds): 6 of
# 8 fell below SR 0.9 at least once and 2 ended there with advantages standardised per minibatch,
# 0 of 8 with `advantage_norm='none'`, which reaches 1.0 later: SG with distractors left chance in
# 1 of 3 seeds by 200,000 unstandardised, 2 of 3 standardised (docs/reproduction_full_budget/
# README.md, "Table I's late collapses"). Not changed: the tables ran these defaults.
# ------------------------------------------------------------------------------------------------
_NAV_PPO = PPOConfig(
    num_envs=64,
    num_steps=64,
    total_timesteps=1_500_000,
    update_epochs=4,
    num_minibatches=32,
    lr=2.5e-4,
    gamma=0.99,
    gae_lambda=0.9,
    clip_eps=0.2,
    ent_coef=0.01,
    vf_coef=0.5,
    max_grad_norm=0.5,
)
TASK_DEFAULTS: dict[str, dict] = {
    # log_every: updates per jitted chunk (one progress / log row each); checkpoint_every: updates.
    'choice': dict(
        ppo=PPOConfig(
            num_envs=64,
            num_steps=4,
            total_timesteps=200_000,
            update_epochs=4,
            num_minibatches=4,
            lr=1e-4,
            gamma=0.99,
            gae_lambda=0.9,
            ent_coef=0.01,
        ),
        log_every=10,
        checkpoint_every=200,
    ),
    'directed': dict(ppo=_NAV_PPO, log_every=1, checkpoint_every=20),
    'exploratory': dict(ppo=_NAV_PPO, log_every=1, checkpoint_every=20),
}

# Named sets of overrides applied before the user's (TrainConfig.preset records which). 'paper':
# what the paper's release ran (PyTorch, PyG <= 2.2, RLlib's PPO of early 2022, 8 envs): its
# camera, the per-relation HGT softmax of PyG <= 2.2, its PPO settings, and RLlib's defaults for
# what the release left unset (ray 1.x PPO: clip_param 0.3, vf_clip_param 10 on the squared value
# error, vf_loss_coeff 1, entropy_coeff 0, kl_coeff 0.2 with kl_target 0.01, no grad_clip,
# advantages standardised over the train batch, torch Adam eps 1e-8).
_PAPER_PPO = {
    'ppo.num_envs': 8,
    'ppo.num_steps': 512,  # train_batch_size 4096 = 8 envs x 512 steps
    'ppo.num_minibatches': 32,  # sgd_minibatch_size 128
    'ppo.update_epochs': 30,
    'ppo.lr': 1e-4,
    'ppo.gamma': 0.99,
    'ppo.gae_lambda': 0.9,
    'ppo.clip_eps': 0.3,
    'ppo.clip_value': False,
    'ppo.vf_loss_clip': 10.0,
    'ppo.vf_coef': 2.0,  # RLlib's vf_loss_coeff 1.0 on the squared error; ours halves it
    'ppo.ent_coef': 0.0,
    'ppo.kl_coeff': 0.2,
    'ppo.kl_target': 0.01,
    'ppo.max_grad_norm': 0.0,
    'ppo.advantage_norm': 'batch',
    'ppo.adam_eps': 1e-8,
    'network.hgt_softmax': 'per_relation',
}
PRESETS: dict[str, dict[str, dict]] = {
    'default': {'choice': {}, 'navigation': {}},
    'paper': {
        'choice': _PAPER_PPO,
        'navigation': {
            **_PAPER_PPO,
            'env.camera.width': 128,
            'env.camera.height': 128,
            'env.map.crop': 128,  # the release's metric map: 128 x 128 cells of 0.23 m
        },
    },
}

DEFAULT_TASK = 'exploratory'
DEFAULT_MODEL = 'rgbd_sg_attn'
MODELS = tuple(VARIANTS)
# Valid values of the numeric fields a user sets (dotted path -> (description, test)); fields not
# listed still pass the generic rules of `_check_value`.
_AT_LEAST_1 = ('>= 1', lambda v: v >= 1)
_NON_NEGATIVE = ('>= 0', lambda v: v >= 0)
_POSITIVE = ('> 0', lambda v: v > 0)
_UNIT = ('in [0, 1]', lambda v: 0 <= v <= 1)
RANGES: dict[str, tuple[str, Any]] = {
    'seed': ('in [0, 2**31)', lambda v: 0 <= v < 2**31),
    'num_seeds': _AT_LEAST_1,
    'log_every': _AT_LEAST_1,
    'checkpoint_every': _AT_LEAST_1,
    'keep_checkpoints': _AT_LEAST_1,
    'ppo.num_envs': _AT_LEAST_1,
    'ppo.num_steps': _AT_LEAST_1,
    'ppo.total_timesteps': _AT_LEAST_1,
    'ppo.update_epochs': _AT_LEAST_1,
    'ppo.num_minibatches': _AT_LEAST_1,
    'ppo.lr': _POSITIVE,
    'ppo.gamma': _UNIT,
    'ppo.gae_lambda': _UNIT,
    'ppo.clip_eps': _POSITIVE,
    'ppo.ent_coef': _NON_NEGATIVE,
    'ppo.vf_coef': _NON_NEGATIVE,
    'ppo.max_grad_norm': ('>= 0 (0: no clipping)', lambda v: v >= 0),
    'ppo.vf_loss_clip': ('>= 0 (0: no clamp)', lambda v: v >= 0),
    'ppo.kl_coeff': ('>= 0 (0: no KL penalty)', lambda v: v >= 0),
    'ppo.kl_target': _POSITIVE,
    'ppo.adam_eps': _POSITIVE,
    'env.max_steps': _AT_LEAST_1,
    'env.success_distance': _POSITIVE,
    'env.num_distractors': _NON_NEGATIVE,
    'env.num_clutter': _NON_NEGATIVE,
    'env.max_distractors': _NON_NEGATIVE,
    'env.min_start_distance': _NON_NEGATIVE,
    'env.image_size': _AT_LEAST_1,
    'env.camera.width': _AT_LEAST_1,
    'env.camera.height': _AT_LEAST_1,
    'env.camera.vfov_deg': ('in (0, 180)', lambda v: 0 < v < 180),
    'env.camera.max_depth': _POSITIVE,
    'env.camera.k_box': _AT_LEAST_1,
    'env.camera.k_sphere': _AT_LEAST_1,
    'env.camera.k_capsule': _AT_LEAST_1,
    'env.camera.row_bands': _AT_LEAST_1,
    'env.camera.k_band': _AT_LEAST_1,
    'env.sim.substeps': _AT_LEAST_1,
    'env.sim.warp_contacts_per_env': _AT_LEAST_1,
    'env.sim.env_dt': _POSITIVE,
    'env.placement.slot_grid': _AT_LEAST_1,
    'env.placement.cell_size': _POSITIVE,
    'env.map.cell': _POSITIVE,
    'env.map.crop': _AT_LEAST_1,
    'env.graph.min_pixels': _AT_LEAST_1,
    'env.graph.detect_range': _POSITIVE,
}

# Fields that follow from other choices: where each is chosen instead.
DERIVED = {
    'env.task': '--task',
    'env.metric_map': '--model rgbd_mm',
    'env.image_obs': '--model-option use_rgbd=...',
    'env.auto_reset': 'nothing (training needs it)',
}
DERIVED.update({f'network.{k}': '--model (it is fixed by the variant)' for v in VARIANTS.values() for k in v})


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a run (hashable). Build it with `make_config`, not directly."""

    task: str
    model: str  # variant name, models.VARIANTS
    env: Any  # NavConfig | ChoiceConfig
    network: ModelConfig
    ppo: PPOConfig
    scene: str | None = None  # repo-relative when inside the repo; None: choice
    seed: int = 0  # seed i of the run uses PRNGKey(seed + i)
    num_seeds: int = 1
    log_every: int = 1  # updates per jitted chunk
    checkpoint_every: int = 20  # updates
    keep_checkpoints: int = 3
    fast_compile: bool = False  # FAST_COMPILE XLA options (tests, debugging)
    preset: str = 'default'  # the PRESETS entry applied under the user's overrides

    @property
    def scene_path(self) -> str | None:
        """Absolute path of the scene file."""
        return None if self.scene is None else resolve(self.scene)

    @property
    def num_updates(self) -> int:
        return self.ppo.num_updates

    @property
    def distractors(self) -> bool:
        return self.env.distractors

    @property
    def premap(self) -> bool:
        return getattr(self.env, 'premap', False)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        """The config of a config.json (checked like a new one); older flat files are upgraded."""
        d = _upgrade(dict(d))
        if 'task' not in d or 'model' not in d:
            raise ConfigError('task' if 'task' not in d else 'model', 'missing from the config')
        rest = _flatten({k: v for k, v in d.items() if k not in ('task', 'model')})
        if d['task'] != 'choice' and 'env.sim.substeps' in rest:
            rest.setdefault('env.sim.physics', 'jax')  # what ran before the field existed
            rest.setdefault('env.sim.collider', 'capsule')  # likewise
        return make_config(d['task'], d['model'], rest)


def make_config(
    task: str = DEFAULT_TASK, model: str = DEFAULT_MODEL, overrides: dict[str, Any] | None = None
) -> TrainConfig:
    """The task's defaults with `overrides` ({dotted field: value}) applied; see the module docstring."""
    if task not in TASKS:
        raise ConfigError('task', f'unknown task {task!r}; valid: {", ".join(TASKS)}')
    if model not in MODELS:
        raise ConfigError('model', f'unknown model {model!r}; valid: {", ".join(MODELS)}')
    overrides = dict(overrides or {})
    if task == 'choice':
        if overrides.get('scene') is not None:
            raise ConfigError('scene', 'the choice task has no scene')
        if overrides.pop('env.premap', False):
            raise ConfigError('env.premap', 'pre-mapping applies to the navigation tasks only')
        if VARIANTS[model].get('use_map'):
            raise ConfigError('model', f'the choice task has no metric map: use another model than {model}')
    size = overrides.pop('env.image_size', None) if task != 'choice' else None
    if size is not None:  # a square camera (ChoiceConfig has a field of that name)
        overrides.setdefault('env.camera.width', size)
        overrides.setdefault('env.camera.height', size)
    preset = overrides.pop('preset', 'default')
    if preset not in PRESETS:
        raise ConfigError('preset', f'unknown preset {preset!r}; valid: {", ".join(PRESETS)}')
    overrides = {**PRESETS[preset]['choice' if task == 'choice' else 'navigation'], **overrides}

    defaults = _defaults(task, model)
    flat = _flatten(dataclasses.asdict(defaults))
    for field, value in overrides.items():
        if field not in flat:
            raise ConfigError(field, f'unknown field; valid: {_siblings(flat, field)}')
        flat[field] = _check_value(field, _coerce(field, value, flat[field]))
    # What follows from the variant and the network: set here, an override may only repeat it.
    derived = {f'network.{k}': v for k, v in VARIANTS[model].items()}
    if task == 'choice':
        derived['env.image_obs'] = flat['network.use_rgbd']
    else:
        derived.update({'env.task': task, 'env.metric_map': flat['network.use_map'], 'env.auto_reset': True})
    for field, value in derived.items():
        if field in overrides and overrides[field] != value:
            raise ConfigError(field, f'is set by {DERIVED[field]}, not directly')
        flat[field] = value
    if flat['scene'] is not None:
        flat['scene'] = portable_path(flat['scene'])
    if 'env.sim.physics' in flat:  # checked and resolved: config.json names what ran, never 'auto'
        from hron_jax.sim import check_collider, resolve_physics

        for field, check in (('env.sim.physics', resolve_physics), ('env.sim.collider', check_collider)):
            try:
                flat[field] = check(flat[field])
            except ValueError as e:
                raise ConfigError(field, str(e)) from None
    flat['preset'] = preset
    return _build(defaults, flat, '')


def override(config: TrainConfig, overrides: dict[str, Any]) -> TrainConfig:
    """`config` with some dotted fields replaced (checked as in make_config)."""
    flat = _flatten({k: v for k, v in dataclasses.asdict(config).items() if k not in ('task', 'model')})
    flat.update(overrides)
    return make_config(config.task, config.model, flat)


def _defaults(task: str, model: str) -> TrainConfig:
    d = TASK_DEFAULTS[task]
    network = dataclasses.replace(ModelConfig(), **VARIANTS[model])
    if task == 'choice' and network.use_graph:
        # The choice task is symbolic (the paper's SG models see only the graph); images are
        # rendered only for a model that asks for them with use_rgbd=True.
        network = dataclasses.replace(network, use_rgbd=False)
    return TrainConfig(
        task=task,
        model=model,
        env=env_config(task),
        network=network,
        ppo=d['ppo'],
        scene=DEFAULT_SCENES.get(task),
        log_every=d['log_every'],
        checkpoint_every=d['checkpoint_every'],
    )


def _flatten(d: dict, prefix: str = '') -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f'{prefix}{k}.'))
        else:
            out[prefix + k] = v
    return out


def _siblings(flat: dict, field: str) -> str:
    prefix = field.rsplit('.', 1)[0] + '.' if '.' in field else ''
    names = sorted(
        {k[len(prefix) :].split('.')[0] for k in flat if k.startswith(prefix) and k not in DERIVED}
    )
    return ', '.join(names)


def _coerce(field: str, value, template):
    """`value` in the type of the field's current value `template` (strings are parsed)."""

    def bad():
        return ConfigError(field, f'expected {type(template).__name__}, got {value!r}')

    if value is None and (template is None or isinstance(template, str)):
        return None
    if isinstance(template, bool):
        if isinstance(value, str):
            if value.lower() in ('1', 'true', 'yes', 'on'):
                return True
            if value.lower() in ('0', 'false', 'no', 'off'):
                return False
            raise bad()
        if not isinstance(value, bool):
            raise bad()
        return value
    if isinstance(template, (tuple, list)):
        items = value.split(',') if isinstance(value, str) else value
        if not isinstance(items, (tuple, list)):
            raise bad()
        kind = type(template[0]) if template else float
        return tuple(_coerce(field, x, kind()) for x in items if x != '')
    if isinstance(template, (int, float)) or template is None:
        kind = type(template) if template is not None else int
        if isinstance(value, str):
            if template is None and value.lower() == 'none':
                return None
            try:
                return kind(value)
            except ValueError:
                raise bad() from None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad()
        if kind is int and value != int(value):
            raise bad()
        return kind(value)
    if isinstance(template, str) and not isinstance(value, str):
        raise bad()
    return value


def _check_value(field: str, value):
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(field, f'must be finite, got {value}')
    if field.startswith('network.') and isinstance(value, (int, tuple)) and not isinstance(value, bool):
        if any(x < 1 for x in (value if isinstance(value, tuple) else (value,))):
            raise ConfigError(field, f'sizes must be >= 1, got {value}')
    if field in RANGES and value is not None:
        what, ok = RANGES[field]
        if not ok(value):
            raise ConfigError(field, f'must be {what}, got {value}')
    return value


def _build(template, flat: dict, prefix: str):
    """The dataclass tree of `template`'s types holding `flat`'s values; the dataclasses' own
    checks (ValueError) become ConfigErrors naming the sub-config."""
    kw = {}
    for f in dataclasses.fields(template):
        cur = getattr(template, f.name)
        path = prefix + f.name
        kw[f.name] = _build(cur, flat, path + '.') if dataclasses.is_dataclass(cur) else flat[path]
    try:
        return type(template)(**kw)
    except ConfigError as e:
        raise (e.under(prefix[:-1]) if prefix else e) from None
    except ValueError as e:
        raise ConfigError(prefix[:-1] or 'config', str(e)) from None


def _upgrade(d: dict) -> dict:
    """A config.json written before the typed tree (flat env_options / model_options) as a tree."""
    if 'env_options' not in d and 'model_options' not in d:
        return d
    out = {
        k: v
        for k, v in d.items()
        if k not in ('env_options', 'model_options', 'distractors', 'premap', 'ppo')
    }
    out.update({f'env.{k}': v for k, v in d.get('env_options', ())})
    out.update({f'network.{k}': v for k, v in d.get('model_options', ())})
    out['env.distractors'] = d.get('distractors', False)
    if d.get('premap'):
        out['env.premap'] = True
    if d.get('task') != 'choice':  # those runs discovered instances from 2 pixels of their own frame
        out.setdefault('env.graph.pixel_reference', dict(d.get('env_options', ())).get('image_size', 32))
    ppo = dict(d.get('ppo', {}))
    ppo.pop('seed', None)
    if 'normalize_advantages' in ppo:
        ppo['advantage_norm'] = 'minibatch' if ppo.pop('normalize_advantages') else 'none'
    out.update({f'ppo.{k}': v for k, v in ppo.items()})
    return out


# Fields that may differ between a run and its resumption (they do not change the computation).
RESUMABLE = ('checkpoint_every', 'keep_checkpoints', 'ppo.total_timesteps')


def config_diff(a: TrainConfig, b: TrainConfig) -> dict[str, tuple]:
    """{dotted field: (a's value, b's value)} where they differ."""
    fa, fb = _flatten(a.to_dict()), _flatten(b.to_dict())
    return {k: (fa.get(k), fb.get(k)) for k in sorted(set(fa) | set(fb)) if fa.get(k) != fb.get(k)}


# ------------------------------------------------------------------------------------------------
# What a config builds and how it is named
# ------------------------------------------------------------------------------------------------


def build_env(config: TrainConfig, episodic: bool = False, **overrides):
    """The run's env with some env config fields overridden. episodic: episodes end instead of
    resetting inside `step` (evaluation and analysis roll out whole episodes)."""
    from hron_jax.envs import make_env

    if episodic and config.task != 'choice':
        overrides = dict(overrides, auto_reset=False)
    return make_env(config.task, config.scene_path, config.env, **overrides)


def build_network(config: TrainConfig, env):
    """The run's ActorCritic for `env` (its actions and its node table's type layout)."""
    from hron_jax.models import make_model

    return make_model(config.model, env.num_actions, config.network, node_type_counts=env.node_type_counts)


def run_label(config: TrainConfig) -> str:
    """The model's name as the paper's tables write it."""
    symbolic = config.task == 'choice' and config.network.use_graph and not config.network.use_rgbd
    return paper_label(config.model, symbolic, config.premap)


def default_run_dir(config: TrainConfig) -> Path:
    parts = [config.task, config.model]
    if config.distractors:
        parts.append('dist')
    if config.premap:
        parts.append('pm')
    parts.append(f's{config.seed}' + (f'x{config.num_seeds}' if config.num_seeds > 1 else ''))
    parts.append(time.strftime('%Y%m%d-%H%M%S'))
    return Path('runs') / '_'.join(parts)
