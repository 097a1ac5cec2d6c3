"""Pipeline config (batchpose/config/): the resolved config and its hash are pinned (template-library cache
keys and every run's config.yaml depend on them), and each field's rules live at the field."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import typing

import pytest

from batchpose.config import (
    ConfigError,
    EstimatorConfig,
    GncConfig,
    apply_overrides,
    config_hash,
    load_estimator_config,
    load_yaml,
    to_dict,
)
from batchpose.config.rules import RULE_KEYS
from tests.conftest import ROOT

# A pin changes only when a default, a field or a pipeline changes on purpose. The template libraries' cache
# keys hash only the sections that make a library (io.library).
DEFAULT_HASH = "3e1d8ab8f0d0ba6a"
DEFAULT_LAYOUT_HASH = "84bf59ecb669f561"  # also pins the fields' order, as config.yaml writes them
PIPELINE_HASHES = {
    "fast.yaml": "0e109e69ba43ae95",
    "gnc_pose.yaml": "3e1d8ab8f0d0ba6a",
    "no_geom_weights.yaml": "9f00ddd2de61eee3",
    "oracle_roi.yaml": "459f90f0e4487393",
    "paper.yaml": "ed3e66089ad3f87a",
    "ransac_only.yaml": "feab3dd4aa21882e",
    "rgbd.yaml": "cd11afdd03215d46",
    "tp_ub.yaml": "b7edeeedbe00d280",
}


def _load(data: dict) -> EstimatorConfig:
    return load_estimator_config(data, "p.yaml")


def _error(data: dict) -> str:
    with pytest.raises(ConfigError) as e:
        _load(data)
    return str(e.value)


def _ruled_fields(cls: type = EstimatorConfig, prefix: str = ""):
    """(dotted key, type, rules) of every field with rules, sections included."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            yield from _ruled_fields(hints[f.name], f"{prefix}{f.name}.")
        elif f.metadata:
            yield f"{prefix}{f.name}", hints[f.name], dict(f.metadata)


def _nested(key: str, value) -> dict:
    *sections, name = key.split(".")
    data: dict = {name: value}
    for s in reversed(sections):
        data = {s: data}
    return data


def test_default_config_and_its_hash_are_pinned():
    conf = EstimatorConfig()
    assert config_hash(conf) == DEFAULT_HASH
    assert hashlib.sha256(json.dumps(to_dict(conf)).encode()).hexdigest()[:16] == DEFAULT_LAYOUT_HASH
    assert _load({}) == conf


@pytest.mark.parametrize("path", sorted((ROOT / "pipelines").glob("*.yaml")), ids=lambda p: p.name)
def test_every_pipeline_loads_to_its_pinned_hash(path):
    conf = load_estimator_config(load_yaml(path), str(path))
    if path.name in PIPELINE_HASHES:
        assert config_hash(conf) == PIPELINE_HASHES[path.name]
    assert load_estimator_config(to_dict(conf)) == conf  # config.yaml reloads to the same config


def test_overrides_reach_the_config():
    data = apply_overrides(load_yaml(ROOT / "pipelines" / "gnc_pose.yaml"), ["gnc.kappa=4", "render.distances_m=[0.3]"])
    conf = _load(data)
    assert conf.gnc.kappa == 4.0 and conf.render.distances_m == (0.3,)
    assert conf == dataclasses.replace(
        EstimatorConfig(),
        gnc=GncConfig(kappa=4.0),
        render=dataclasses.replace(EstimatorConfig().render, distances_m=(0.3,)),
    )


def test_rules_live_at_the_fields_and_the_defaults_keep_them():
    ruled = list(_ruled_fields())
    assert len(ruled) == 148
    for key, tp, rules in ruled:
        assert set(rules) <= set(RULE_KEYS), key
        if "choices" in rules:
            assert tp is str and set(rules) == {"choices"}, key
    assert _load({}) == EstimatorConfig()  # every default meets its own rules


@pytest.mark.parametrize(
    "data, message",
    [
        ({"gnc": {"kappa": 0}}, "p.yaml: gnc.kappa must be positive, got 0.0"),
        ({"gnc": {"gamma": 1}}, "p.yaml: gnc.gamma must be in (0, 1), got 1.0"),
        ({"gnc": {"min_inliers": 3}}, "p.yaml: gnc.min_inliers must be >= 4 (PnP), got 3"),
        ({"track": {"min_match": 1.0}}, "p.yaml: track.min_match must be in [0, 1), got 1.0"),
        ({"render": {"min_elevation_deg": 90}}, "p.yaml: render.min_elevation_deg must be in [-90, 90), got 90.0"),
        ({"render": {"width": 8}}, "p.yaml: render.width must be 0 (the camera's) or >= 16, got 8"),
        ({"features": {"n_features": -1}}, "p.yaml: features.n_features must be >= 0 (0: no limit), got -1"),
        ({"features": {"retry_sigma": -1}}, "p.yaml: features.retry_sigma must be 0 (off) or positive, got -1.0"),
        (
            {"render": {"image_fractions": [0.5, 1.5]}},
            "p.yaml: render.image_fractions must be a non-empty list of values in (0, 1], got [0.5, 1.5]",
        ),
        ({"render": {"distances_m": [0.0]}}, "p.yaml: render.distances_m must be a list of positive values, got [0.0]"),
    ],
)
def test_a_value_out_of_bounds_is_a_one_line_error(data, message):
    assert _error(data) == message


@pytest.mark.parametrize("key, tp, rules", list(_ruled_fields()), ids=lambda x: x if isinstance(x, str) else "")
def test_every_bound_holds_exactly_where_it_says(key, tp, rules):
    """Inclusive bounds accept the bound, exclusive ones refuse it, and a step outside is refused."""
    if "choices" in rules:
        assert _error(_nested(key, "nope")).startswith(f"p.yaml: {key} = 'nope', expected one of ")
        return
    step = 1 if tp is int else 0.5
    wrap = (lambda v: [v]) if typing.get_origin(tp) is tuple else (lambda v: v)
    for name, inside, outside in (("ge", True, -step), ("gt", False, 0), ("le", True, step), ("lt", False, 0)):
        if name not in rules:
            continue
        bound = rules[name]
        bound_ok = inside or ("off" in rules and bound == 0)
        if bound_ok:
            _load(_nested(key, wrap(bound)))
        else:
            assert _error(_nested(key, wrap(bound))).startswith(f"p.yaml: {rules.get('subject', key)} must be ")
        if outside:
            bad = bound + outside
            if "off" in rules and bad == 0:
                continue
            assert _error(_nested(key, wrap(bad))).startswith(f"p.yaml: {rules.get('subject', key)} must be ")


def test_a_bad_choice_is_a_one_line_error():
    assert _error({"match": {"direction": "sideways"}}) == (
        "p.yaml: match.direction = 'sideways', expected one of template_to_query, query_to_template"
    )
    assert _error({"method": "gnc"}) == "p.yaml: method = 'gnc', expected one of gnc_pose, tp_ub"


def test_an_unknown_key_names_its_dotted_path_and_the_nearest_key():
    gnc_keys = ", ".join(f.name for f in dataclasses.fields(GncConfig))
    top_keys = ", ".join(f.name for f in dataclasses.fields(EstimatorConfig))
    assert _error({"gnc": {"kapa": 3}}) == (
        f"p.yaml: gnc: unknown key kapa, did you mean 'gnc.kappa'? (expected one of: {gnc_keys})"
    )
    assert _error({"gnc": {"kapa": 3, "gama": 0.5, "zzz": 1}}) == (
        "p.yaml: gnc: unknown keys gama, kapa, zzz, did you mean 'gnc.gamma' for gama, 'gnc.kappa' for kapa? "
        f"(expected one of: {gnc_keys})"
    )
    assert _error({"trak": {}}) == f"p.yaml: unknown key trak, did you mean 'track'? (expected one of: {top_keys})"
    assert _error({"zzz": 1}) == f"p.yaml: unknown key zzz (expected one of: {top_keys})"
    # --set takes the same dotted path the hint gives, and its own mistakes are blamed on --set.
    with pytest.raises(ConfigError, match="^--set gnc.kapa=3: unknown key gnc.kapa; did you mean gnc.kappa\\?$"):
        apply_overrides({}, ["gnc.kapa=3"])
    assert _load(apply_overrides({}, ["gnc.kappa=3"])).gnc.kappa == 3.0


def test_a_key_given_twice_is_a_one_line_error(tmp_path):
    """PyYAML would keep the last of two equal keys and drop the first without a word."""
    path = tmp_path / "p.yaml"
    path.write_text("gnc:\n  kappa: 3\n  kappa: 4\nmin_confidence: 0.2\n")
    with pytest.raises(ConfigError, match=r"^.*p\.yaml: not valid YAML: key 'kappa' given twice \(line 3\)$"):
        load_yaml(path)
    path.write_text("gnc:\n  kappa: 3\nmin_confidence: 0.2\n")
    assert load_yaml(path) == {"gnc": {"kappa": 3}, "min_confidence": 0.2}


@pytest.mark.parametrize(
    "data, message",
    [
        (
            {"features": {"retry_contrast_threshold": 0.02}},
            "p.yaml: features.retry_contrast_threshold must be 0 (off) or below features.contrast_threshold (0.02), "
            "got 0.02",
        ),
        ({"render": {"znear_m": 20}}, "p.yaml: render.znear_m must be positive and below render.zfar_m, got 20.0"),
        (
            {"depth": {"gate_m": 0.01, "gate_final_m": 0.02}},
            "p.yaml: depth.gate_final_m must be positive and at most gate_m, got 0.02",
        ),
        ({"depth": {"max_points": 40}}, "p.yaml: depth.max_points must be >= min_pixels, got 40"),
    ],
)
def test_cross_field_rules_are_one_line_errors(data, message):
    assert _error(data) == message
