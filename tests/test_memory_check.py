"""A frame that does not fit in memory exits 3 before any work (shadowlab.render.memory): the estimate
from the G-buffer and the light views, the CPU's free memory, and compare / sweep / fit / gate
refusing a huge frame with the memory needed and free named and nothing written."""

from pathlib import Path

import pytest

from conftest import llvm_only  # noqa: E402  (tests/ is on the path)
from shadowlab import cli
from shadowlab.errors import EnvironmentProblem
from shadowlab.render import memory
from shadowlab.scene.spec import scene_spec
from shadowlab.techniques import base

#: 16 lights (cube maps among them) at 8192², maps of 8192²: about 81 GiB, more than any CPU here (an
#: H200's 139 GiB holds it: these tests read the CPU's real free memory, the GPU's refusal is tested
#: with a small device below)
HUGE_ON_GPU = "an H200 holds many_lights at 8192² with 8192² maps (about 81 GiB)"
HUGE = ["many_lights", "--resolution", "8192x8192"]


def _mem_available() -> int:
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) * 1024
    pytest.skip("no MemAvailable in /proc/meminfo")


@llvm_only("on a GPU the free memory is the device's (cuMemGetInfo), not the host's")
def test_free_memory_on_the_cpu_is_memavailable(mitsuba_backend):
    free, where = memory.free_memory()
    assert "MemAvailable" in where
    assert abs(free - _mem_available()) < max(256 << 20, 0.05 * free)


def test_the_need_is_the_gbuffer_and_the_largest_techniques_maps():
    spec = scene_spec("two_lights", (64, 32))
    lights = spec.lights
    assert len(lights) == 2 and all(l.kind != "point" for l in lights)
    gb = 64 * 32 * (memory.GBUFFER_BYTES + 2 * memory.LIGHT_BYTES)
    assert memory.gbuffer_bytes(64, 32, lights=2) == gb
    assert memory.gbuffer_bytes(64, 32, ss=2, lights=2) == 4 * gb
    hard = base.get("hard").resolve({"resolution": 512})
    csm = base.get("csm").resolve({"resolution": 256, "cascades": 4})
    n = memory.frame_need(spec, {"hard": hard, "csm": csm, "sdf_hard": base.get("sdf_hard").resolve({})})
    t_hard = 2 * 512 ** 2 * memory.VIEW_BYTES + 512 ** 2 * memory.BUILD_BYTES
    t_csm = 2 * 4 * 256 ** 2 * memory.VIEW_BYTES + 256 ** 2 * memory.BUILD_BYTES
    assert n.gbuffer == gb and n.views == max(t_hard, t_csm) and n.total == gb + n.views
    assert n.technique == ("hard" if t_hard > t_csm else "csm")
    side = lights[0].shadow_map                           # resolution 0: the light's own map
    assert memory.light_maps(spec, base.get("hard").resolve({})) == ((1, side, 1), (1, lights[1].shadow_map, 1))
    assert memory.light_maps(spec, base.get("sdf_hard").resolve({})) == ()


def test_a_point_light_casts_six_faces():
    spec = scene_spec("many_lights", (32, 32))
    maps = memory.light_maps(spec, base.get("hard").resolve({"resolution": 128}))
    assert [m[0] for m in maps] == [6 if l.kind == "point" else 1 for l in spec.lights]
    assert 6 in [m[0] for m in maps]


def test_check_fits_names_needed_free_and_the_fix():
    spec = scene_spec("contact", (256, 256))
    hard = {"hard": base.get("hard").resolve({"resolution": 2048})}
    need = memory.frame_need(spec, hard)
    assert memory.check_fits(spec, hard, free=(need.total, "test")) == need
    with pytest.raises(EnvironmentProblem) as e:
        memory.check_fits(spec, hard, free=(need.total - 1, "free on the test device"))
    msg = str(e.value)
    assert e.value.exit_code == 3
    assert f"{need.total / memory.GiB:.1f} GiB" in msg and "free on the test device" in msg
    assert "--set hard.resolution=512" in msg and "--resolution" in msg


@pytest.mark.parametrize("command", [
    ["compare", *HUGE, "-t", "hard", "--set", "hard.resolution=8192", "--out", "{out}"],
    ["sweep", *HUGE, "--technique", "hard", "--param", "resolution=4096:8192:2", "--out", "{out}"],
    ["fit", *HUGE, "--technique", "pcss", "--set", "pcss.resolution=8192", "--out", "{out}",
     "--save-preset", "{out}.toml"],
], ids=["compare", "sweep", "fit"])
@llvm_only(HUGE_ON_GPU)
def test_a_frame_that_does_not_fit_exits_3_before_any_work(command, tmp_path, capsys, mitsuba_backend):
    out = tmp_path / "out"
    before = sorted(tmp_path.rglob("*"))
    rc = cli.main([a.replace("{out}", str(out)) for a in command])
    err = capsys.readouterr().err
    assert rc == 3, err
    assert "needs about" in err and "GiB" in err and "MemAvailable" in err and "--resolution" in err, err
    assert sorted(tmp_path.rglob("*")) == before


@llvm_only(HUGE_ON_GPU)
def test_a_gate_that_does_not_fit_exits_3_before_any_gate_runs(tmp_path, capsys, mitsuba_backend):
    (tmp_path / "store").mkdir()
    gates = tmp_path / "store" / "gates.toml"
    gates.write_text('version = 1\n[[gate]]\nname = "huge"\nscene = "many_lights"\nresolution = [8192, 8192]\n'
                     'candidate = { technique = "hard", params = { resolution = 8192 } }\nbudget = { rmse = 1.0 }\n')
    rc = cli.main(["gate", str(gates), "--out", str(tmp_path / "g")])
    err = capsys.readouterr().err
    assert rc == 3 and "needs about" in err, err
    assert not (tmp_path / "g").exists() and sorted(p.name for p in (tmp_path / "store").iterdir()) == ["gates.toml"]


def test_bench_frames_checks_every_scene_before_it_measures(tmp_path, capsys, monkeypatch, mitsuba_backend):
    # the CPU's own figure is tested above; here the device is made small, so the refusal is certain
    monkeypatch.setattr(memory, "free_memory", lambda: (1 << 20, "free on a test device"))
    rc = cli.main(["bench", "--only", "frames", "--size", "64x36", "--out", str(tmp_path / "b")])
    err = capsys.readouterr().err
    assert rc == 3 and "needs about" in err and "free on a test device" in err and "a smaller --size" in err, err
    assert not (tmp_path / "b").exists()
