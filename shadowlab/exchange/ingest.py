"""``shadowlab ingest SCENE IMAGE.exr``: compare an image rendered elsewhere with the stored truth.

Two kinds of image (docs/ARCHITECTURE.md, Reference; README.md, "Exchange with other renderers"):

* ``--channel NAME`` (repeatable): one light's **visibility** in [0, 1], a single EXR channel.
  The light is named by ``NAME=LIGHT``, else by a dot-separated part of NAME that is a light name
  (``shadow.key`` → ``key``), else it is the scene's only light. Compared with the truth's
  ``V.<light>`` (the ratio of shadowed to unshadowed direct light, ``--against V``, default) or
  ``A.<light>`` (the plain visible fraction of the light, ``--against A``) where the light reaches
  the pixel (hit mask and U > 0), with ``compare_visibility``; the shaded image
  Σ_L U_L · V_L with the ingested visibility for these lights (the truth's for the others) is
  compared with the truth's with ``compare_shaded`` — the numbers ``shadowlab compare`` reports.
* ``--shaded``: an RGB image of the direct light (channels ``R, G, B`` or ``<layer>.R|G|B``) in
  the units of ``lights.json`` (radiance), compared with the truth's ``shaded`` image (pixel
  centres, ``--against shaded``, default) or Mitsuba's ``direct`` image (box-filtered pixels,
  ``--against mitsuba``).

Bad input (exit 2, nothing written): a missing image or channel (the message lists the image's
channels), an image whose size has no stored reference (the message lists the stored sizes and
the command that renders one), a stale reference, NaN/Inf (count and first pixel), a ``--channel``
with values outside [0, 1] (not a visibility). The truth is only read; a report goes to ``--out``
(never into the reference store).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError, ReferenceError_
from ..gate import check, parse_thresholds
from ..gate.gatefile import read_toml
from ..io.exr import check_finite, read_exr
from ..metrics import compare_shaded, compare_visibility, penumbra_mask
from ..reference import store
from ..report import Run, build
from ..report.lights import light_info
from ..io.outdir import claim_dir
from ..scene.spec import load_spec, resolve

__all__ = ["ingest", "CHANNEL_AGAINST", "SHADED_AGAINST"]

CHANNEL_AGAINST = ("V", "A")
SHADED_AGAINST = ("shaded", "mitsuba")


def channel_labels(labels, channel_of: dict) -> dict:
    """``--label CHANNEL=TEXT`` (repeatable) -> {light: TEXT}; ``channel_of``: {light: channel}.

    >>> channel_labels(["shadow.key=engine PCF 5x5"], {"key": "shadow.key"})
    {'key': 'engine PCF 5x5'}
    """
    light_of = {c: n for n, c in channel_of.items()}
    out = {}
    for item in labels or ():
        name, sep, text = item.partition("=")
        name, text = name.strip(), text.strip()
        if not sep or not name or not text:
            raise InputError(f"--label {item!r}: expected CHANNEL=TEXT (a channel given with --channel) or a plain "
                             "TEXT for the image")
        if name not in light_of:
            raise InputError(f"--label {item!r}: {name!r} is not one of the --channel channels "
                             f"({', '.join(light_of) or 'none: --shaded has no channels'})")
        out[light_of[name]] = text
    return out


def default_out(scene: str, image, root: Path = Path("reports/ingest")) -> Path:
    """The default report directory of an ingest: reports/ingest/SCENE-IMAGE, with -2, -3, … added
    when that exists already, so a new ingest never overwrites the previous one."""
    stem = f"{Path(scene).stem}-{Path(image).stem}"
    p, k = root / stem, 2
    while p.exists():
        p, k = root / f"{stem}-{k}", k + 1
    return p


def _channel_list(ch: dict) -> str:
    names = sorted(ch)
    shown = ", ".join(names[:40]) + (f", … ({len(names)} in all)" if len(names) > 40 else "")
    return shown


def _light_of(name: str, explicit: str | None, lights: list[str], image: Path) -> str:
    if explicit is not None:
        if explicit not in lights:
            raise InputError(f"--channel {name}={explicit}: the scene has no light {explicit!r}; its lights: "
                             f"{', '.join(lights)}")
        return explicit
    parts = [p for p in name.split(".") if p in lights]
    if len(set(parts)) == 1:
        return parts[0]
    if len(lights) == 1:
        return lights[0]
    raise InputError(f"--channel {name}: cannot tell which light it is (the scene has {', '.join(lights)}); "
                     f"write --channel {name}=LIGHT")


def _pick_shaded(ch: dict, layer: str | None, image: Path):
    if layer is not None:
        names = [f"{layer}.{c}" for c in "RGB"]
    elif all(c in ch for c in "RGB"):
        names = list("RGB")
    else:
        layers = sorted({n[:-2] for n in ch if n.endswith(".R") and n[:-2] + ".G" in ch and n[:-2] + ".B" in ch})
        if len(layers) != 1:
            raise InputError(f"{image}: --shaded needs channels R, G, B or one layer LAYER.R|G|B; "
                             + (f"it has the layers {', '.join(layers)}: pick one with --layer"
                                if layers else f"its channels are {_channel_list(ch)}"))
        names = [f"{layers[0]}.{c}" for c in "RGB"]
    missing = [n for n in names if n not in ch]
    if missing:
        raise InputError(f"{image} has no channel(s) {', '.join(missing)}; its channels are {_channel_list(ch)}")
    return names, np.stack([ch[n] for n in names], -1).astype(np.float64)


def _finite(image: Path, what: str, a: np.ndarray) -> None:
    check_finite(f"{image}: {what}", a)  # count and first pixel (x, y), row 0 at the top


VIS_TOL = 1e-3  # how far outside [0, 1] a visibility channel may stray (half-float round-off)
#: how far below 0 a radiance may go, as a fraction of the image's largest magnitude (round-off)
NEG_TOL = 1e-4


def _non_negative(image: Path, what: str, a: np.ndarray) -> None:
    """Radiance is never negative: values below ``-NEG_TOL × max|a|`` mean a difference image, a
    denoiser's ringing or the wrong layer, which would compare as a plausible error."""
    bad = a < -NEG_TOL * max(float(np.abs(a).max()), 1e-30)
    n = int(bad.any(axis=-1).sum()) if a.ndim == 3 else int(bad.sum())
    if n:
        y, x = (int(v) for v in np.argwhere(bad)[0][:2])
        raise InputError(f"{image}: {what} is meant to be radiance (never negative) but {n} pixel"
                         f"{'s have' if n != 1 else ' has'} negative values (minimum {a.min():.4g}, the first at "
                         f"x={x}, y={y}); give the direct light itself (clamp a denoiser's output at 0), not a "
                         "difference image or another layer")


def _in_unit_range(image: Path, name: str, a: np.ndarray) -> None:
    """A visibility is a fraction: values well outside [0, 1] mean the wrong channel (radiance,
    0..255, depth) was named."""
    bad = (a < -VIS_TOL) | (a > 1 + VIS_TOL)
    n = int(bad.sum())
    if n:
        y, x = (int(v) for v in np.argwhere(bad)[0])
        raise InputError(f"{image}: channel {name!r} is meant to be a light's visibility in [0, 1] but {n} pixel"
                         f"{'s are' if n != 1 else ' is'} outside it (range {a.min():.4g} .. {a.max():.4g}, the first "
                         f"at x={x}, y={y}); name the visibility channel, or use --shaded for an RGB image of the "
                         "direct light")


def _extra_stats(x, t, se, valid) -> dict:
    """Signed mean error and the truth's own noise over ``valid`` (noise-aware reading of the RMSE)."""
    if not valid.any():
        return {"bias": float("nan"), "truth_se_rms": float("nan")}
    d = (x - t)[valid]
    return {"bias": float(d.mean()), "truth_se_rms": float(np.sqrt(np.mean(np.asarray(se)[valid] ** 2)))}


def ingest(scene, image, *, channels=(), shaded: bool = False, layer: str | None = None,
           against: str | None = None, resolution=None, out=None, base=None, gate=None,
           label: str | None = None, labels=(), force: bool = False) -> dict:
    """Compare ``image`` (an EXR) with the stored truth of ``scene``; returns the run dict (what
    ``metrics.json`` holds, plus ``images``). ``out``: write index.html, summary.md and
    metrics.json there (:func:`shadowlab.report.build`). ``resolution``: the reference's (W, H);
    default the image's size. ``gate``: a gate file, run on the image (exit 1 when it fails).
    ``out`` is never inside the store, and an existing directory shadowlab did not make is
    written into only with ``force`` (:func:`shadowlab.io.outdir.claim_dir`). ``label``: the
    image's name in the report (default its file name); ``labels``: ``CHANNEL=TEXT`` titles of
    channels (``--label``), shown beside their light."""

    spec = load_spec(resolve(scene))
    image = Path(image)
    base = Path(base) if base is not None else None
    channels = list(channels or [])
    if shaded and channels:
        raise InputError("give either --channel (a light's visibility) or --shaded (an RGB image), not both")
    if not shaded and not channels:
        hint = ""
        if image.exists():
            try:
                hint = f"; {image} has the channels {_channel_list(read_exr(image))}"
            except InputError:
                pass
        raise InputError("say what the image holds: --channel NAME (a light's visibility, e.g. --channel "
                         f"shadow.{spec.lights[0].name}) or --shaded (RGB direct light)" + hint)
    allowed = SHADED_AGAINST if shaded else CHANNEL_AGAINST
    against = against or allowed[0]
    if against not in allowed:
        raise InputError(f"--against {against}: with {'--shaded' if shaded else '--channel'} compare against one of "
                         f"{', '.join(allowed)}")
    if layer is not None and not shaded:
        raise InputError("--layer picks the RGB layer of --shaded; with --channel name the channel itself")
    if out is not None:
        claim_dir(Path(out), "ingest", force=force, protected=[base or store.root()])

    g = _load_gate(gate) if gate is not None else None
    ch = read_exr(image)
    lights = [l.name for l in spec.lights]
    picked = {}  # light -> (channel name, H×W array)
    rgb_names = None
    if shaded:
        rgb_names, img = _pick_shaded(ch, layer, image)
        hw = img.shape[:2]
    else:
        for c in channels:
            name, _, explicit = c.partition("=")
            name, explicit = name.strip(), (explicit.strip() or None)
            if name not in ch:
                raise InputError(f"{image} has no channel {name!r}; its channels are {_channel_list(ch)}")
            light = _light_of(name, explicit, lights, image)
            if light in picked:
                raise InputError(f"--channel {c}: light {light!r} already comes from channel {picked[light][0]!r}")
            picked[light] = (name, ch[name].astype(np.float64))
        hw = next(iter(picked.values()))[1].shape
    H, W = (int(x) for x in hw)
    res = tuple(resolution) if resolution else (W, H)
    if res != (W, H):
        raise InputError(f"{image} is {W}x{H} but the reference asked for is {res[0]}x{res[1]}; render the image at "
                         f"{res[0]}x{res[1]}, or compare with a reference of the image's size: "
                         f"`shadowlab reference {store.scene_arg(spec)} --resolution {W}x{H}`")
    spec = spec.with_resolution(*res)  # the scene hash includes the camera resolution
    try:
        truth, meta = store.load(spec, res, base)
    except ReferenceError_ as e:
        raise ReferenceError_(f"{image} is {W}x{H}: {e}") from None
    if shaded:
        _finite(image, f"the RGB image ({', '.join(rgb_names)})", img)
        _non_negative(image, f"the RGB image ({', '.join(rgb_names)})", img)
    else:
        for light, (name, a) in picked.items():
            _finite(image, f"channel {name!r}", a)
            _in_unit_range(image, name, a)

    mask = np.asarray(truth.mask, bool)
    lit = {n: mask & (np.asarray(truth.U[n]).sum(-1) > 0) for n in lights}
    truth_vis = {n: np.asarray(truth.lights[n].A if against == "A" else truth.lights[n].V, np.float64)
                 for n in lights}
    truth_se = {n: np.asarray(truth.lights[n].A_se if against == "A" else truth.lights[n].V_se, np.float64)
                for n in lights}
    label = label or image.name
    titles = channel_labels(labels, {n: picked[n][0] for n in picked} if not shaded else {})
    per_light, vis_imgs = {}, {}
    notes = []
    if int(meta.get("supersampling", 1)) > 1:
        notes.append(f"the reference averages {meta['supersampling']}x{meta['supersampling']} shading points per "
                     "pixel; an image shaded at pixel centres differs from it along edges")
    if shaded:
        run_lights = []
        pen = np.zeros_like(mask)
        for n in lights:
            pen |= penumbra_mask(truth.lights[n].V, lit[n])
        if against == "mitsuba":
            if truth.mitsuba is None:
                raise InputError(
                    "the reference has no mitsuba.R|G|B channels (rendered with --spp 0); use "
                    f"--against shaded or re-render it: `shadowlab reference {store.scene_arg(spec)} --resolution "
                    f"{W}x{H} --force`"
                )
            t_img, t_var = np.asarray(truth.mitsuba, np.float64), np.asarray(truth.mitsuba_var, np.float64)
        else:
            t_img, t_var = np.asarray(truth.shaded, np.float64), np.asarray(truth.shaded_var, np.float64)
        m = compare_shaded(img, t_img, penumbra=pen, valid=mask)
        m.update(_extra_stats(img.mean(-1), t_img.mean(-1), np.sqrt(t_var.mean(-1)), mask))
        shaded_img = img
    else:
        run_lights = [n for n in lights if n in picked]
        vis = {}
        pen = np.zeros_like(mask)
        pooled = {"leak": [0, 0], "overdark": [0, 0]}
        for n in run_lights:
            v, tv = picked[n][1], truth_vis[n]
            valid = lit[n]
            per_light[n] = {**compare_visibility(v, tv, valid), **_extra_stats(v, tv, truth_se[n], valid),
                            "channel": picked[n][0]}
            vis[n] = v
            vis_imgs[n] = np.where(valid, v, tv)
            pen |= penumbra_mask(tv, valid)
            umbra, lt = valid & (tv <= 0.02), valid & (tv >= 0.98)
            pooled["leak"][0] += int((umbra & (v > 0.5)).sum())
            pooled["leak"][1] += int(umbra.sum())
            pooled["overdark"][0] += int((lt & (v < 0.5)).sum())
            pooled["overdark"][1] += int(lt.sum())
        shaded_img = sum(np.asarray(truth.U[n], np.float64) * np.where(lit[n], vis.get(n, truth_vis[n]), 0)[..., None]
                         for n in lights)
        t_img = sum(np.asarray(truth.U[n], np.float64) * np.where(lit[n], truth_vis[n], 0)[..., None] for n in lights)
        m = compare_shaded(shaded_img, t_img, penumbra=pen, valid=mask)
        m["leak_rate"] = pooled["leak"][0] / pooled["leak"][1] if pooled["leak"][1] else 0.0
        m["overdark_rate"] = pooled["overdark"][0] / pooled["overdark"][1] if pooled["overdark"][1] else 0.0
        m["vis_rmse"] = float(np.mean([d["rmse"] for d in per_light.values()]))
        pr = [d["rmse_penumbra"] for d in per_light.values()]
        m["vis_rmse_penumbra"] = float(np.nanmean(pr)) if any(np.isfinite(pr)) else float("nan")
        if against == "A":
            notes.append("--against A: the shaded images on both sides are composed with the plain visible "
                         "fraction A (not the truth's shaded image)")

    # metrics.json keeps numbers in "metrics" / "per_light" (the channel name goes to params)
    per_light_num = {n: {k: v for k, v in d.items() if k != "channel"} for n, d in per_light.items()}
    run = {
        "scene": spec.name,
        "resolution": [W, H],
        "reference": {
            "spp": float(np.mean(list(meta["samples"]["mean_rays_per_pixel"].values()))),
            "rays_per_pixel": meta["samples"]["mean_rays_per_pixel"],
            "max_std_error": meta["max_std_error"],
            "seed": meta.get("seed"),
            "supersampling": int(meta.get("supersampling", 1)),
            "path": str(store.path_for(spec.name, res, base, frame=spec.frame)),
            "scene_hash": meta.get("scene_hash"),
        },
        "lights": run_lights,
        "light_info": light_info(spec.lights),  # the report's light summary (kind, size, what the truth is)
        "ingest": {
            "image": str(image),
            "mode": "shaded" if shaded else "visibility",
            "against": against,
            "channels": ({n: picked[n][0] for n in run_lights} if not shaded else {"rgb": rgb_names}),
            "notes": notes,
            "labels": titles,
        },
        "techniques": {
            label: {
                "params": {
                    "image": str(image),
                    "against": against,
                    **({"channels": {n: picked[n][0] for n in run_lights}} if not shaded else {"rgb": rgb_names}),
                },
                "time_s": None,
                "metrics": m,
                "per_light": per_light_num,
            }
        },
        "images": {
            "truth": {"shaded": t_img, "vis": {n: truth_vis[n] for n in run_lights}},
            "techniques": {label: {"shaded": shaded_img, "vis": vis_imgs}},
        },
    }
    if truth.mitsuba is not None and shaded:
        run["images"]["mitsuba"] = np.asarray(truth.mitsuba, np.float64)
    if gate is not None:
        run["gate"] = _gate_results(g, truth, ch, image, shaded, img if shaded else None, picked, against, lit)
    run = Run.from_mapping(run)
    if out is not None:
        build(Path(out), run, force=force, protected=[base or store.root()], kind="ingest")
    return run


GATE_KEYS = ("name", "statistical", "budget", "std_error", "variance")


def _load_gate(path) -> dict:
    """The ingest gate file: one gate's thresholds (the keys of a ``[[gate]]`` table of a
    :mod:`shadowlab.gate` file that concern the comparison) as TOML::

        name = "engine/parallel_planes"      # optional, default the file's stem
        statistical = {}                     # Z-test per pixel + bias tests (settings or {} = defaults)
        budget = { rmse_penumbra = 0.02 }    # limits on the metrics
        std_error = "shadow.key.se"          # optional: the image's own per-pixel standard error
        # (--channel: a channel or a table {light = channel}; --shaded: a layer with .R/.G/.B);
        # or variance = ... (same forms)

    The target follows the ingest: each --channel light's visibility (V, or A with --against A),
    or the shaded / mitsuba image with --shaded."""
    p = Path(path)
    data = read_toml(p, f"--gate {path}", "write a TOML file with statistical = {} and/or budget = { rmse = 0.05 }")
    unknown = sorted(set(data) - set(GATE_KEYS))
    if unknown:
        raise InputError(f"--gate {path}: unknown key(s) {', '.join(unknown)}; allowed: {', '.join(GATE_KEYS)} "
                         "(the image and the reference come from the ingest command line)")
    if "std_error" in data and "variance" in data:
        raise InputError(f"--gate {path}: give std_error or variance, not both")
    parse_thresholds({k: data[k] for k in ("statistical", "budget") if k in data}, where=f"--gate {path}")
    return {
        "name": str(data.get("name", p.stem)),
        "thresholds": {k: data[k] for k in ("statistical", "budget") if k in data},
        "spread": ("std_error", data["std_error"])
        if "std_error" in data
        else ("variance", data["variance"])
        if "variance" in data
        else None,
        "path": str(p),
    }


def _spread_channel(g, ch, light, image, shaded):
    """The candidate's variance (H×W or H×W×3) from the gate's std_error / variance key, or None."""
    if g["spread"] is None:
        return None
    kind, spec = g["spread"]
    if shaded:
        if not isinstance(spec, str):
            raise InputError(f"--gate {g['path']}: {kind} must be a layer name (LAYER.R|G|B) with --shaded")
        names = [f"{spec}.{c}" for c in "RGB"]
    else:
        name = spec.get(light) if isinstance(spec, dict) else spec
        if not isinstance(name, str):
            raise InputError(f"--gate {g['path']}: {kind} has no channel for light {light!r}; write "
                             f"{kind} = {{ {light} = \"CHANNEL\" }}")
        names = [name]
    missing = [n for n in names if n not in ch]
    if missing:
        raise InputError(f"--gate {g['path']}: {image} has no {kind} channel(s) {', '.join(missing)}; its channels are "
                         f"{_channel_list(ch)}")
    a = np.stack([ch[n].astype(np.float64) for n in names], -1)
    a = a[..., 0] if a.shape[-1] == 1 else a
    _finite(image, f"{kind} channel(s) {', '.join(names)}", a)
    if (a < 0).any():
        raise InputError(f"{image}: {kind} channel(s) {', '.join(names)} hold negative values")
    return a * a if kind == "std_error" else a


def _gate_results(g, truth, ch, image, shaded, img, picked, against, lit) -> dict:
    """Run the gate on the ingested image; returns the JSON summary stored in the run."""
    results = []
    if shaded:
        var = _spread_channel(g, ch, None, image, True)
        results.append(check(img, truth, g["thresholds"], target=against, candidate_var=var, name=g["name"]))
    else:
        for light, (name, v) in picked.items():
            var = _spread_channel(g, ch, light, image, False)
            gname = g["name"] if len(picked) == 1 else f"{g['name']}/{light}"
            if against == "V":
                results.append(check(v, truth, g["thresholds"], target="visibility", light=light, candidate_var=var,
                                     name=gname))
            else:  # the plain visible fraction A: the truth image as an array, with its variance
                lt = truth.lights[light]
                ref_var = np.asarray(lt.A_se, np.float64) ** 2 + (np.asarray(lt.bound, np.float64) / 2) ** 2
                results.append(check(v, np.asarray(lt.A, np.float64), g["thresholds"], target="visibility",
                                     light=light, candidate_var=var, reference_var=ref_var, valid=lit[light],
                                     name=gname))
    lines = [ln for r in results for ln in r.lines()]
    failed = [f"{r.name} {c.name}" for r in results for c in r.failed]
    checks = [{"gate": r.name, "check": c.name, "kind": c.kind, "value": c.value, "threshold": c.threshold,
               "op": c.op, "passed": c.passed, "text": c.text} for r in results for c in r.checks]
    return {"file": g["path"], "passed": not failed, "failed": failed, "lines": lines, "checks": checks}
