"""Method variants: a preset's `variants:` section maps a name to per-section config overrides.

Selects the full method (`pig`), the ablations of Section 4.5 (`no_precond`, `fixed_anchors`, `no_offsets`,
`single_mlp`, body-parameter noise `noise_<sigma>`), the LOD table's single-level model (`lod_1of1`), offsets in
the anchor's frame (`local_offsets`) and a baseline bound to the template (`template_bound`); no paper equation.
"""
from __future__ import annotations

from typing import Any

from pig.config import ConfigError


def variant_overrides(preset: dict[str, Any], name: str) -> dict[str, dict[str, Any]]:
    """{section: {key: value}} of variant `name`; `pig` with no entry means no overrides."""
    variants = preset.get("variants") or {}
    where = f"{preset.get('_path', '<preset>')}: section 'variants'"
    if not isinstance(variants, dict):
        raise ConfigError(f"{where}: expected a mapping of variant name -> overrides")
    if name not in variants:
        if name == "pig":
            return {}
        raise ConfigError(f"{where}: unknown variant {name!r}; expected one of {sorted(variants)}")
    overrides = variants[name] or {}
    if not isinstance(overrides, dict) or not all(isinstance(v, dict) for v in overrides.values()):
        raise ConfigError(f"{where}.{name}: expected a mapping of section -> {{key: value}}, found {overrides!r}")
    return {section: dict(values) for section, values in overrides.items()}


def variant_kind(preset: dict[str, Any], name: str) -> str:
    """`noise` (the variant sets fit.sigma_body), `lod` (it sets avatar.levels) or `structural` (any other, `pig`
    included): which of the paper's tables the variant belongs to besides the main one."""
    overrides = variant_overrides(preset, name)
    if "sigma_body" in overrides.get("fit", {}):
        return "noise"
    if "levels" in overrides.get("avatar", {}):
        return "lod"
    return "structural"


def table_variants(preset: dict[str, Any], names: list[str], table: str) -> list[str]:
    """The variants of `names` in a table, in their order: all of them in `main` and `regions`; the structural
    ones in `ablation`; `pig` (sigma 0) and the noise variants in `noise`."""
    if table in ("main", "regions"):
        return list(names)
    if table == "ablation":
        return [name for name in names if variant_kind(preset, name) == "structural"]
    if table == "noise":
        return [name for name in names if name == "pig" or variant_kind(preset, name) == "noise"]
    raise ConfigError(f"unknown table {table!r}; expected main, ablation, noise or regions")
