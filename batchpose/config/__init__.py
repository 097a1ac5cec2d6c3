"""Pipeline configuration: frozen dataclasses whose defaults are SPEC.md's values.

A pipeline YAML (``pipelines/*.yaml``) sets any subset of these fields; unknown keys are an error.
``--set section.field=value`` overrides one field (the value is parsed as YAML).

- :mod:`.rules`: :func:`knob`, a field's choices and bounds next to its default, and the one validator.
- :mod:`.sections`: one dataclass per step of the method (mesh, render, features, ..., track, carry, depth);
  :mod:`.plane`: the plane search's.
- :mod:`.estimator`: :class:`EstimatorConfig` (the sections plus the fields that span them) and
  :func:`validate`, with the few rules that tie two fields together.
- :mod:`.load`: YAML, ``--set`` overrides, dict to config and back, the config hash of cache keys.
- :mod:`.pipelines`: the bundled pipeline YAMLs by name (``resolve``, ``available``) and the Foxglove layout
  template (``layout_template``), found alike in a checkout and in an installed wheel.
"""

from batchpose.config.estimator import EstimatorConfig, validate
from batchpose.config.load import (
    apply_overrides,
    config_hash,
    from_dict,
    load_estimator_config,
    load_yaml,
    to_dict,
)
from batchpose.config.plane import PlaneConfig
from batchpose.config.rules import knob
from batchpose.config.sections import (
    CarryConfig,
    DepthConfig,
    FeatureConfig,
    FineConfig,
    GncConfig,
    MatchConfig,
    MeshConfig,
    RefineConfig,
    RegionConfig,
    RenderConfig,
    TrackConfig,
    WeightsConfig,
)
from batchpose.errors import ConfigError

__all__ = [
    "CarryConfig",
    "ConfigError",
    "DepthConfig",
    "EstimatorConfig",
    "FeatureConfig",
    "FineConfig",
    "GncConfig",
    "MatchConfig",
    "MeshConfig",
    "PlaneConfig",
    "RefineConfig",
    "RegionConfig",
    "RenderConfig",
    "TrackConfig",
    "WeightsConfig",
    "apply_overrides",
    "config_hash",
    "from_dict",
    "knob",
    "load_estimator_config",
    "load_yaml",
    "to_dict",
    "validate",
]
