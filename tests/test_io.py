"""EXR and JSON I/O: bit-exact round trips, atomic writes, clear errors on bad files."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from shadowlab.errors import EnvironmentProblem, InputError
from shadowlab.io import exr as exr_mod
from shadowlab.io.exr import check_finite, read_exr, rgb_channels, split_rgb, stack_rgb, write_exr
from shadowlab.io.jsonio import read_json, write_json_atomic

ODD_NAMES = ["V.key", "V.key.se", "shaded.R", "shaded.G", "shaded.B", "R", "G", "B", "A", "a b.c", "ünï.cödé", "x" * 60]


def _tricky_float32(rng, shape):
    a = rng.standard_normal(shape).astype(np.float32) * np.float32(1e3)
    flat = a.reshape(-1)
    specials = np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 1e-45, -1e-45, 3.4e38, 1e-38, 0.02, 0.98],
                        dtype=np.float32)
    flat[: specials.size] = specials
    return a


def _bits(a):
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


def _listing(d):
    return sorted(os.listdir(d))


def test_exr_round_trip_is_bit_exact_with_odd_channel_names(tmp_path):
    rng = np.random.default_rng(1)
    channels = {n: _tricky_float32(rng, (17, 23)) for n in ODD_NAMES}
    path = tmp_path / "frame.exr"
    write_exr(path, channels)
    back = read_exr(path)
    assert set(back) == set(ODD_NAMES)
    for name, arr in channels.items():
        assert back[name].dtype == np.float32
        assert back[name].shape == (17, 23)
        np.testing.assert_array_equal(_bits(back[name]), _bits(arr))  # incl. NaN, -0.0, denormals


def test_exr_is_zip_compressed_float(tmp_path):
    import OpenEXR

    path = tmp_path / "c.exr"
    write_exr(path, {"V.key": np.zeros((8, 8))})
    with OpenEXR.File(str(path), separate_channels=True) as f:
        assert f.header()["compression"] == OpenEXR.ZIP_COMPRESSION
        assert f.channels()["V.key"].type() == OpenEXR.FLOAT


def test_exr_write_coerces_to_float32_and_does_not_mutate_input(tmp_path):
    src = {"V.key": np.linspace(0, 1, 12).reshape(3, 4)}  # float64
    write_exr(tmp_path / "a.exr", src)
    assert isinstance(src["V.key"], np.ndarray) and src["V.key"].dtype == np.float64
    back = read_exr(tmp_path / "a.exr")["V.key"]
    np.testing.assert_array_equal(back, src["V.key"].astype(np.float32))


def test_exr_write_leaves_no_temporary_file(tmp_path):
    write_exr(tmp_path / "a.exr", {"V.key": np.ones((4, 4))})
    write_exr(tmp_path / "a.exr", {"V.key": np.zeros((4, 4))})  # overwrite
    assert _listing(tmp_path) == ["a.exr"]
    assert read_exr(tmp_path / "a.exr")["V.key"].max() == 0.0


def test_exr_overwrite_false_keeps_existing_file_untouched(tmp_path):
    path = tmp_path / "ref.exr"
    write_exr(path, {"V.key": np.ones((4, 4))})
    before = path.read_bytes()
    mtime = os.stat(path).st_mtime_ns
    with pytest.raises(InputError, match="already exists"):
        write_exr(path, {"V.key": np.zeros((4, 4))}, overwrite=False)
    assert path.read_bytes() == before
    assert os.stat(path).st_mtime_ns == mtime
    assert _listing(tmp_path) == ["ref.exr"]


def test_exr_overwrite_false_writes_a_new_file(tmp_path):
    write_exr(tmp_path / "new.exr", {"V.key": np.ones((2, 2))}, overwrite=False)
    assert _listing(tmp_path) == ["new.exr"]
    assert read_exr(tmp_path / "new.exr")["V.key"].min() == 1.0


def test_exr_failed_write_keeps_old_file_and_removes_temp(tmp_path, monkeypatch):
    path = tmp_path / "ref.exr"
    write_exr(path, {"V.key": np.ones((4, 4))})
    before = path.read_bytes()

    def boom(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(exr_mod.os, "replace", boom)
    with pytest.raises(EnvironmentProblem, match="cannot write .*free disk space"):  # the machine's: exit 3
        write_exr(path, {"V.key": np.zeros((4, 4))})
    assert path.read_bytes() == before
    assert _listing(tmp_path) == ["ref.exr"]


def test_exr_write_creates_parent_directories(tmp_path):
    path = tmp_path / "a" / "b" / "v.exr"
    write_exr(path, {"V.key": np.ones((2, 2))})
    assert path.is_file()


@pytest.mark.parametrize(
    "channels, match",
    [
        ({}, "non-empty"),
        ({"V.key": np.ones((2, 2)), "V.fill": np.ones((2, 3))}, "same H×W"),
        ({"shaded": np.ones((2, 2, 3))}, "split_rgb"),
        ({"": np.ones((2, 2))}, "channel name"),
    ],
)
def test_exr_write_rejects_bad_channels(tmp_path, channels, match):
    with pytest.raises(InputError, match=match):
        write_exr(tmp_path / "bad.exr", channels)
    assert _listing(tmp_path) == []


def test_read_exr_missing_file_names_it(tmp_path):
    path = tmp_path / "nope.exr"
    with pytest.raises(InputError, match="nope.exr"):
        read_exr(path)


def test_read_exr_not_an_exr(tmp_path):
    path = tmp_path / "text.exr"
    path.write_text("this is not an image\n" * 10)
    with pytest.raises(InputError, match="text.exr.*not an OpenEXR"):
        read_exr(path)


@pytest.mark.parametrize("keep", [0.9, 0.5, 0.05])
def test_read_exr_truncated_file_raises_input_error(tmp_path, keep):
    rng = np.random.default_rng(2)
    good = tmp_path / "good.exr"
    write_exr(good, {"V.key": rng.random((64, 64), dtype=np.float32)})
    data = good.read_bytes()
    bad = tmp_path / "bad.exr"
    bad.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(InputError, match="bad.exr"):
        read_exr(bad)


def test_read_exr_directory(tmp_path):
    with pytest.raises(InputError, match="not a file"):
        read_exr(tmp_path)


def test_rgb_helpers_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    img = rng.random((5, 7, 3), dtype=np.float32)
    assert rgb_channels("shaded") == ["shaded.R", "shaded.G", "shaded.B"]
    ch = split_rgb(img, "shaded")
    assert list(ch) == rgb_channels("shaded")
    write_exr(tmp_path / "s.exr", {**ch, "V.key": img[..., 0]})
    back = read_exr(tmp_path / "s.exr")
    np.testing.assert_array_equal(stack_rgb(back, "shaded"), img)
    with pytest.raises(InputError, match="missing channel"):
        stack_rgb(back, "direct")
    with pytest.raises(InputError, match="H×W×3"):
        split_rgb(img[..., :2], "x")


def test_check_finite_reports_count_first_pixel_and_fix():
    a = np.zeros((4, 5), np.float32)
    check_finite("vis", a)  # no error
    a[2, 3] = np.nan
    a[3, 1] = np.inf
    with pytest.raises(InputError) as info:
        check_finite("vis", a)
    msg = str(info.value)
    assert "vis" in msg and "2 non-finite" in msg
    assert "(x=3, y=2)" in msg  # row-major first: row 2 before row 3
    assert "clamp or remove non-finite values" in msg
    check_finite("vis", a, mask=np.zeros((4, 5), bool))  # outside the mask: fine
    rgb = np.zeros((3, 3, 3))
    rgb[1, 2, 1] = -np.inf
    with pytest.raises(InputError, match=r"1 non-finite value .*\(x=2, y=1\)"):
        check_finite("img", rgb)


def test_json_round_trip_numpy_and_order(tmp_path):
    path = tmp_path / "meta.json"
    obj = {
        "z_first": 1,
        "rmse": np.float32(0.25),
        "count": np.int64(7),
        "ok": np.bool_(True),
        "shape": np.array([2, 3]),
        "nested": {"arr": np.eye(2), "t": (1, 2.5)},
        "psnr": float("inf"),
        "empty": float("nan"),
    }
    write_json_atomic(path, obj)
    back = read_json(path)
    assert list(back) == list(obj)  # insertion order, not sorted
    assert back["rmse"] == 0.25 and back["count"] == 7 and back["ok"] is True
    assert back["shape"] == [2, 3] and back["nested"] == {"arr": [[1.0, 0.0], [0.0, 1.0]], "t": [1, 2.5]}
    assert back["psnr"] == math.inf and math.isnan(back["empty"])
    assert '  "z_first": 1' in path.read_text()  # indent 2
    assert _listing(tmp_path) == ["meta.json"]


def test_json_failed_write_keeps_old_file(tmp_path, monkeypatch):
    import shadowlab.io.jsonio as jsonio

    path = tmp_path / "meta.json"
    write_json_atomic(path, {"a": 1})
    monkeypatch.setattr(jsonio.os, "replace", lambda s, d: (_ for _ in ()).throw(OSError("disk")))
    with pytest.raises(EnvironmentProblem, match="cannot write"):  # the machine's: exit 3
        write_json_atomic(path, {"a": 2})
    assert read_json(path) == {"a": 1}
    assert _listing(tmp_path) == ["meta.json"]


def test_read_json_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="missing.json"):
        read_json(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"a": 1,,}')
    with pytest.raises(InputError, match="bad.json.*malformed"):
        read_json(bad)
