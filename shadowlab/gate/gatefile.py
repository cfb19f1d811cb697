"""Gate files (TOML): which candidate is compared with which stored reference, and the thresholds.

A gate file is validated as a whole before anything is rendered or read (syntax, keys, ranges,
scene and light names, technique names and parameters, candidate files, budget metrics per target);
every error names the file, the gate and the key. The format is documented in
:mod:`shadowlab.gate` and in the README (section "CI gates").
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - python < 3.11
    import tomli as tomllib

from ..errors import InputError, SceneError
from ..pipeline import frame_list
from ..reference.location import chosen as chosen_store
from ..reference.truth import SEED_MAX
from ..scene.reader import check_param_values, did_you_mean
from ..scene.spec import load_spec, resolve
from ..techniques import base as tbase
from .check import TARGETS
from .thresholds import (SHADED_METRICS, STAT_DEFAULTS, TECHNIQUE_SHADED_METRICS, VISIBILITY_METRICS, Thresholds,
                         parse_thresholds)

__all__ = ["CandidateSpec", "GateSpec", "GateFile", "load_gate_file", "parse_gate_file", "FORMAT_VERSION"]

FORMAT_VERSION = 1
_TOP_KEYS = ("version", "references", "defaults", "gate")
_GATE_KEYS = ("name", "description", "scene", "resolution", "frame", "frames", "target", "light", "candidate",
              "statistical", "budget")
_CAND_KEYS = {"technique": ("technique", "params"), "exr": ("exr", "channel", "variance", "std_error"),
              "truth": ("truth", "seed")}


@dataclass(frozen=True)
class CandidateSpec:
    """``kind``: ``technique`` (``technique`` run with ``params`` on the scene's frame),
    ``exr`` (an image file: ``path``, ``channel`` prefix, optional ``variance`` / ``std_error``
    channel) or ``truth`` (the ground truth rendered now with this shadowlab at ``seed``)."""

    kind: str
    technique: str | None = None
    params: dict = field(default_factory=dict)
    path: Path | None = None
    channel: str | None = None
    variance: str | None = None
    std_error: str | None = None
    seed: int | None = None

    def describe(self) -> str:
        if self.kind == "technique":
            ps = ", ".join(f"{k}={v}" for k, v in self.params.items())
            return f"technique {self.technique}" + (f" ({ps})" if ps else "")
        if self.kind == "truth":
            return f"ground truth rendered now, seed {self.seed}"
        return f"EXR {self.path}" + (f" [{self.channel}]" if self.channel else "")


@dataclass(frozen=True)
class GateSpec:
    name: str
    scene: str                    # built-in name or absolute path of a .toml
    resolution: tuple | None
    target: str
    light: str | None
    candidate: CandidateSpec
    thresholds: Thresholds
    description: str = ""
    frame: int | None = None      # the camera path frame gated (None: the scene as it is)
    group: str | None = None      # the gate file's name of a gate expanded over frames (``frames``)

    def at_frame(self, f: int) -> "GateSpec":
        """This gate at frame ``f``, named ``<name>@frame<f>`` (``--only <name>`` still selects it)."""
        group = self.group or self.name
        return replace(self, frame=f, name=f"{group}@frame{f}", group=group)


@dataclass(frozen=True)
class GateFile:
    path: Path
    references: Path              # the reference store these gates read
    gates: tuple

    def select(self, names) -> list:
        if not names:
            return list(self.gates)
        have = {g.name: g for g in self.gates}
        groups = {}
        for g in self.gates:
            if g.group:
                groups.setdefault(g.group, []).append(g)
        missing = [n for n in names if n not in have and n not in groups]
        if missing:
            raise InputError(f"{self.path}: no gate named {', '.join(map(repr, missing))}; its gates: "
                             f"{', '.join(dict.fromkeys([g.group or g.name for g in self.gates]))}")
        return [g for n in names for g in ([have[n]] if n in have else groups[n])]




def _keys(where: str, table: Mapping, allowed) -> None:
    unknown = [k for k in table if k not in allowed]
    if unknown:
        hints = "".join(did_you_mean(k, allowed) for k in unknown[:1])
        raise InputError(f"{where}: unknown key(s) {', '.join(map(repr, unknown))}{hints}; allowed: "
                         f"{', '.join(allowed)}. Fix the spelling or remove the key")


def _technique(where: str, name: str):
    """The registered technique ``name``, or an InputError suggesting the closest name."""
    if name not in tbase.names() and not tbase.composes(name):
        raise InputError(f"{where}: unknown technique {name!r}{did_you_mean(name, tbase.names())}; registered "
                         f"techniques: {', '.join(tbase.names())}")
    return tbase.get(name)


def _str(where: str, key: str, v, required=False) -> str | None:
    if v is None:
        if required:
            raise InputError(f"{where}: missing required key {key!r}")
        return None
    if not isinstance(v, str) or not v.strip():
        raise InputError(f"{where}: {key} must be a non-empty string, got {v!r}")
    return v


def _scene(where: str, base: Path, v) -> tuple[str, object]:
    s = _str(where, "scene", v, required=True)
    if s.endswith(".toml"):
        p = Path(s) if Path(s).is_absolute() else (base / s)
        s = str(p.resolve())
    try:
        return s, load_spec(resolve(s))
    except SceneError as e:
        raise InputError(f"{where}: scene: {e}") from None


def _candidate(where: str, base: Path, v, target: str, spec) -> CandidateSpec:
    w = f"{where}.candidate"
    if not isinstance(v, Mapping):
        raise InputError(f"{where}: missing or malformed `candidate`: give a table with one of "
                         "technique = \"NAME\" (+ params), exr = \"FILE.exr\" (+ channel) or truth = true (+ seed)")
    kinds = [k for k in _CAND_KEYS if k in v]
    if len(kinds) != 1:
        every = sorted({k for ks in _CAND_KEYS.values() for k in ks})
        odd = [k for k in v if k not in every]
        hint = f"; unknown key {odd[0]!r}{did_you_mean(odd[0], every)}" if odd else ""
        raise InputError(f"{w}: give exactly one of technique, exr, truth (got {', '.join(kinds) or 'none'}){hint}")
    kind = kinds[0]
    _keys(w, v, _CAND_KEYS[kind])
    if kind == "technique":
        name = _str(w, "technique", v["technique"])
        params = v.get("params", {})
        if not isinstance(params, Mapping):
            raise InputError(f"{w}: params must be a table such as params = {{ kernel = 5 }}, got {params!r}")
        t = _technique(w, name)
        check_param_values(w, t, params)
        try:
            t.resolve(dict(params))  # out-of-range values raise here
        except InputError as e:
            raise InputError(f"{w}: {e}") from None
        return CandidateSpec("technique", technique=name, params=dict(params))
    if kind == "truth":
        if v["truth"] is not True:
            raise InputError(f"{w}: truth must be true (render the ground truth now), got {v['truth']!r}")
        seed = v.get("seed")
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0 or seed > SEED_MAX:
            raise InputError(f"{w}: a truth candidate needs seed = N (an integer in 0..{SEED_MAX} other than the "
                             f"reference's seed), got {seed!r}")
        return CandidateSpec("truth", seed=seed)
    p = Path(_str(w, "exr", v["exr"]))
    p = p if p.is_absolute() else base / p
    if not p.is_file():
        raise InputError(f"{w}: candidate image {p} does not exist; write it first or fix the path "
                         "(relative paths are relative to the gate file)")
    var, se = _str(w, "variance", v.get("variance")), _str(w, "std_error", v.get("std_error"))
    if var and se:
        raise InputError(f"{w}: give variance or std_error, not both")
    return CandidateSpec("exr", path=p, channel=_str(w, "channel", v.get("channel")), variance=var, std_error=se)


def _stat_keys(where: str, table: Mapping) -> None:
    odd = [k for k in table if k not in STAT_DEFAULTS]
    if odd:
        raise InputError(
            f"{where}: unknown statistical setting(s) {', '.join(odd)}{did_you_mean(odd[0], STAT_DEFAULTS)}; "
            f"known: {', '.join(STAT_DEFAULTS)}"
        )


def _resolution(where: str, v):
    if v is None:
        return None
    if (not isinstance(v, list) or len(v) != 2 or any(isinstance(x, bool) or not isinstance(x, int) for x in v)
            or min(v) < 1 or max(v) > 8192):
        raise InputError(f"{where}: resolution must be [WIDTH, HEIGHT] with integers in 1..8192, got {v!r}")
    return tuple(v)


def gate_frames(where: str, spec, frame=None, frames=None) -> list | None:
    """The frames a gate runs at: ``frame = N`` or ``frames = "A:B"`` / ``[A, B]`` (both ends
    included), each checked against the scene's camera path (exit 2 naming the valid range)."""
    if frame is not None and frames is not None:
        raise InputError(f"{where}: give frame = N or frames = \"A:B\", not both")
    if frame is not None and (isinstance(frame, bool) or not isinstance(frame, int)):
        raise InputError(f"{where}: frame must be an integer frame index, got {frame!r}")
    if frames is not None:
        ok = (isinstance(frames, str) and frames.count(":") == 1) or (
            isinstance(frames, list) and len(frames) == 2 and all(isinstance(x, int) and not isinstance(x, bool)
                                                                 for x in frames))
        if not ok:
            raise InputError(
                f"{where}: frames must be \"A:B\" or [A, B] (frame indices, both included), got {frames!r}"
            )
    try:
        return frame_list(spec, frame, frames)
    except (InputError, SceneError) as e:
        raise InputError(f"{where}: {e}") from None


def parse_gate_file(data: Mapping, path: Path) -> GateFile:
    """A validated :class:`GateFile` from parsed TOML ``data`` read from ``path``."""
    path = Path(path)
    base = path.resolve().parent
    where = str(path)
    if "camera" in data and "gate" not in data:
        raise InputError(f"{where}: this is a scene file ([camera], [[lights]]), not a gate file; give a gate file "
                         "(version, references, [[gate]] tables; e.g. references/gates.toml), or use the scene with "
                         f"`shadowlab compare {path} ...` / `shadowlab reference {path}`")
    _keys(where, data, _TOP_KEYS)
    ver = data.get("version", FORMAT_VERSION)
    if isinstance(ver, bool) or ver != FORMAT_VERSION:
        raise InputError(f"{where}: version = {ver!r} is not supported; this shadowlab reads version {FORMAT_VERSION}")
    refs = data.get("references", ".")
    if not isinstance(refs, str):
        raise InputError(f"{where}: references must be a path (relative to the gate file), got {refs!r}")
    refs = Path(refs) if Path(refs).is_absolute() else (base / refs)
    refs = chosen_store() or refs                      # `shadowlab gate --references DIR` overrides the file
    defaults = data.get("defaults", {})
    if not isinstance(defaults, Mapping):
        raise InputError(f"{where}: [defaults] must be a table")
    _keys(f"{where} [defaults]", defaults, ("statistical",))
    stat_defaults = defaults.get("statistical", {})
    if not isinstance(stat_defaults, Mapping):
        raise InputError(f"{where} [defaults]: statistical must be a table")
    _stat_keys(f"{where} [defaults.statistical]", stat_defaults)
    gates = data.get("gate")
    if not isinstance(gates, list) or not gates or not all(isinstance(g, Mapping) for g in gates):
        raise InputError(f"{where}: no gates: add one or more [[gate]] tables (name, scene, candidate, "
                         "statistical and/or budget)")
    out, seen = [], set()
    for i, g in enumerate(gates):
        gname = g.get("name")
        w = f"{where}: gate {gname!r}" if isinstance(gname, str) else f"{where}: gate #{i + 1}"
        _keys(w, g, _GATE_KEYS)
        name = _str(w, "name", gname, required=True)
        if name in seen:
            raise InputError(f"{w}: the name is used twice; gate names must be unique")
        seen.add(name)
        scene, spec = _scene(w, base, g.get("scene"))
        res = _resolution(w, g.get("resolution"))
        target = g.get("target", "shaded")
        if not isinstance(target, str) or target not in TARGETS:
            raise InputError(f"{w}: target = {target!r}{did_you_mean(target, TARGETS)}; one of {', '.join(TARGETS)}")
        lights = [l.name for l in spec.lights]
        light = _str(w, "light", g.get("light"))
        if target == "visibility":
            if light is None:
                if len(lights) != 1:
                    raise InputError(f"{w}: target visibility needs light = one of {', '.join(lights)}")
                light = lights[0]
            elif light not in lights:
                raise InputError(f"{w}: light {light!r} is not in scene {spec.name!r}; its lights: {', '.join(lights)}")
        elif light is not None:
            raise InputError(f"{w}: light is only used with target = \"visibility\"")
        cand = _candidate(w, base, g.get("candidate"), target, spec)
        if isinstance(g.get("statistical"), Mapping):
            _stat_keys(f"{w}.statistical", g["statistical"])
        if isinstance(g.get("budget"), Mapping):
            metrics = tuple(dict.fromkeys(SHADED_METRICS + TECHNIQUE_SHADED_METRICS + VISIBILITY_METRICS))
            odd = [k for k in g["budget"] if k not in metrics]
            if odd:
                raise InputError(f"{w}: unknown budget metric {odd[0]!r}{did_you_mean(odd[0], metrics)}; known: "
                                 f"{', '.join(metrics)}")
        th = parse_thresholds({k: g[k] for k in ("statistical", "budget") if k in g}, where=w,
                              stat_defaults=stat_defaults)
        allowed = VISIBILITY_METRICS if target == "visibility" else (
            SHADED_METRICS + (TECHNIQUE_SHADED_METRICS if cand.kind == "technique" else ()))
        bad = [k for k in th.budget if k not in allowed]
        if bad:
            extra = (" (leak/over-darkening rates and vis_rmse of a shaded target need a technique candidate;"
                     " for an image use target = \"visibility\")" if set(bad) & set(TECHNIQUE_SHADED_METRICS) else "")
            raise InputError(f"{w}: budget metric(s) {', '.join(bad)} do not exist for target {target!r}{extra}; "
                             f"available: {', '.join(allowed)}")
        desc = g.get("description", "")
        if not isinstance(desc, str):
            raise InputError(f"{w}: description must be a string")
        gs = GateSpec(name, scene, res, target, light, cand, th, desc)
        sel = gate_frames(w, spec, g.get("frame"), g.get("frames"))
        if sel is None:
            out.append(gs)
        elif "frame" in g:
            out.append(replace(gs, frame=sel[0]))
        else:
            out.extend(gs.at_frame(f) for f in sel)
    return GateFile(path=path, references=refs, gates=tuple(out))


def read_toml(path, label: str, missing: str) -> dict:
    """The TOML file ``path`` as a dict; a missing file or bad syntax raises :class:`InputError`
    naming ``label`` (``missing``: what to give instead)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{label} does not exist; {missing}")
    try:
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{label}: not valid TOML ({e}); fix the syntax at the position given") from None


def load_gate_file(path) -> GateFile:
    """Read and validate a gate file; any problem raises :class:`InputError` naming file, gate and key."""
    p = Path(path)
    data = read_toml(p, f"gate file {p}", "give the path of a TOML gate file such as references/gates.toml")
    return parse_gate_file(data, p)
