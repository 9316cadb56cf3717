"""FLAME loading from fake FLAME pickles (same keys and types), and the restricted unpickler."""

import os
import pickle
import subprocess
import functools

import numpy as np
import pytest
import torch

from geoavatar.head import HeadModel, load_head_data
from geoavatar.head.flame import (
    FLAME_LIP_RING_LOWER, FLAME_LIP_RING_UPPER, FlameFileNotFoundError, load_flame,
)
from geoavatar.io.safe_pickle import ForbiddenPickleGlobal, load_restricted_pickle, loads_restricted
from head_fakes import procedural_head, renumber_to_flame, write_fake_flame


@pytest.fixture(scope="module")
def small_head():
    return procedural_head()


@pytest.fixture(scope="module")
def flame_sized_head(small_head):
    return renumber_to_flame(small_head, 5023)


def _reversed_rings(data):
    """Lip rings stored from the subject's left corner to the right, to check the loader reorients them."""
    return {"lip_ring_upper": data.lip_ring_upper[::-1].copy(), "lip_ring_lower": data.lip_ring_lower[::-1].copy()}


def test_small_fake_flame_loads_every_array(tmp_path, small_head):
    write_fake_flame(tmp_path, small_head, "2023", masks_extra=_reversed_rings(small_head))
    data = load_flame(tmp_path)
    assert data.name == "flame"
    np.testing.assert_allclose(data.v_template, small_head.v_template, atol=1e-7)
    np.testing.assert_array_equal(data.faces, small_head.faces)
    assert data.shapedirs.shape == (small_head.num_vertices, 3, 300)
    assert data.exprdirs.shape == (small_head.num_vertices, 3, 100)
    np.testing.assert_allclose(data.shapedirs[:, :, :8], small_head.shapedirs)
    np.testing.assert_allclose(data.exprdirs[:, :, :4], small_head.exprdirs)
    assert not data.shapedirs[:, :, 8:].any() and not data.exprdirs[:, :, 4:].any()
    np.testing.assert_allclose(data.j_regressor, small_head.j_regressor, atol=1e-7)
    np.testing.assert_allclose(data.lbs_weights, small_head.lbs_weights)
    np.testing.assert_allclose(data.posedirs, small_head.posedirs, atol=1e-7)
    for name, ids in small_head.regions.items():
        np.testing.assert_array_equal(data.regions[name], ids)
    # Rings came from the masks file in decreasing x; stored in increasing x.
    np.testing.assert_array_equal(data.lip_ring_upper, small_head.lip_ring_upper)
    np.testing.assert_array_equal(data.lip_ring_lower, small_head.lip_ring_lower)
    assert data.landmark_faces is None and data.landmark_ids is None
    meta = data.metadata
    assert meta["version"] == "2023" and meta["num_shape"] == 300 and meta["num_expr"] == 100
    assert meta["source"].endswith("flame2023.pkl")


def test_flame_through_load_head_model_runs_forward(tmp_path, small_head):
    write_fake_flame(tmp_path, small_head, "2023", masks_extra=_reversed_rings(small_head))
    head = HeadModel(load_head_data("flame", mouth="geoavatar", flame_dir=str(tmp_path)))
    params = head.zero_params(2)
    params["jaw_pose"] = torch.tensor([[0.2, 0, 0], [0.0, 0, 0]])
    out = head.forward_params(params)
    assert out.vertices.shape == (2, head.num_vertices, 3)
    assert torch.allclose(out.vertices[1], head.v_template, atol=1e-5)


def test_5023_vertex_fake_gets_flame_lip_ring_ids(tmp_path, flame_sized_head):
    write_fake_flame(tmp_path, flame_sized_head, "2020")  # no ring keys in the masks: FLAME ids are used
    data = load_flame(tmp_path, version="auto")
    assert data.num_vertices == 5023 and data.metadata["version"] == "2020"
    assert set(data.lip_ring_upper.tolist()) == set(FLAME_LIP_RING_UPPER)
    assert set(data.lip_ring_lower.tolist()) == set(FLAME_LIP_RING_LOWER)
    for ring in (data.lip_ring_upper, data.lip_ring_lower):
        assert np.all(np.diff(data.v_template[ring, 0]) > 0)  # subject's right -> left
    np.testing.assert_array_equal(data.lip_ring_upper, flame_sized_head.lip_ring_upper)


def test_small_fake_without_lip_rings_is_refused(tmp_path, small_head):
    write_fake_flame(tmp_path, small_head, "2023")
    with pytest.raises(ValueError, match="lip_ring_upper"):
        load_flame(tmp_path)


def test_auto_prefers_2023_and_explicit_version(tmp_path, small_head):
    rings = _reversed_rings(small_head)
    write_fake_flame(tmp_path, small_head, "2020", masks_extra=rings)
    write_fake_flame(tmp_path, small_head.copy_with(v_template=small_head.v_template * 2), "2023", masks_extra=rings)
    auto = load_flame(tmp_path)
    assert auto.metadata["version"] == "2023"
    np.testing.assert_allclose(auto.v_template, small_head.v_template * 2, atol=1e-6)
    assert load_flame(tmp_path, version="2020").metadata["version"] == "2020"
    with pytest.raises(ValueError, match="version"):
        load_flame(tmp_path, version="2017")


def test_env_var_names_the_folder(tmp_path, small_head, monkeypatch):
    write_fake_flame(tmp_path, small_head, "2023", masks_extra=_reversed_rings(small_head))
    monkeypatch.setenv("GEOAVATAR_FLAME_DIR", str(tmp_path))
    assert load_flame().metadata["source"] == str(tmp_path / "flame2023.pkl")


def test_missing_files_say_what_where_and_how(tmp_path, small_head, monkeypatch):
    monkeypatch.delenv("GEOAVATAR_FLAME_DIR", raising=False)
    with pytest.raises(FlameFileNotFoundError, match="GEOAVATAR_FLAME_DIR") as err:
        load_flame()
    assert isinstance(err.value, FileNotFoundError) and "flame.is.tue.mpg.de" in str(err.value)

    with pytest.raises(FlameFileNotFoundError, match="does not exist"):
        load_flame(tmp_path / "nowhere")

    with pytest.raises(FlameFileNotFoundError) as err:
        load_flame(tmp_path)
    message = str(err.value)
    for needle in ("flame2023.pkl", "generic_model.pkl", str(tmp_path), "--flame-dir", "register"):
        assert needle in message

    write_fake_flame(tmp_path, small_head, "2023", write_masks=False)
    with pytest.raises(FlameFileNotFoundError) as err:
        load_flame(tmp_path)
    assert "FLAME_masks.pkl" in str(err.value) and "FLAME Vertex Masks" in str(err.value)

    with pytest.raises(FlameFileNotFoundError, match="generic_model.pkl"):
        load_flame(tmp_path, version="2020")


class _RunsCommand:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


class _CallsEval:
    def __reduce__(self):
        return (eval, ("__import__('os').getcwd()",))


class _Popen:
    def __reduce__(self):
        return (subprocess.Popen, (["true"],))


class _Partial:
    def __reduce__(self):
        return (functools.partial, (print, "hi"))


def test_unpickler_refuses_code_without_running_it(tmp_path, small_head):
    marker = tmp_path / "pwned"
    write_fake_flame(tmp_path, small_head, "2023", masks_extra=_reversed_rings(small_head))
    evil = {"v_template": np.zeros((3, 3)), "f": _RunsCommand(marker)}
    (tmp_path / "flame2023.pkl").write_bytes(pickle.dumps(evil, protocol=2))
    with pytest.raises(ForbiddenPickleGlobal) as err:
        load_flame(tmp_path)
    assert str(tmp_path / "flame2023.pkl") in str(err.value)
    assert f"{os.system.__module__}.system" in str(err.value)  # posix.system on Linux
    assert not marker.exists()


@pytest.mark.parametrize("payload, forbidden", [
    (_CallsEval(), "builtins.eval"), (_Popen(), "subprocess.Popen"), (_Partial(), "functools.partial"),
])
def test_unpickler_refuses_other_callables(payload, forbidden):
    with pytest.raises(ForbiddenPickleGlobal, match=forbidden):
        loads_restricted(pickle.dumps({"masks": [payload]}, protocol=4), source="masks.pkl")  # py3 names


def test_python2_style_array_pickle_loads():
    """numpy arrays pickled by Python 2 store their bytes as latin1 str: the FLAME files' case."""
    raw = np.arange(3, dtype="<f4").tobytes()
    data = (b"\x80\x02cnumpy.core.multiarray\n_reconstruct\nq\x00cnumpy\nndarray\nq\x01K\x00\x85q\x02U\x01b"
            b"\x87q\x03Rq\x04(K\x01K\x03\x85cnumpy\ndtype\nq\x05U\x02f4K\x00K\x01\x87Rq\x06(K\x03U\x01<NNNJ"
            b"\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00tb\x89U" + bytes([len(raw)]) + raw + b"tb.")
    np.testing.assert_array_equal(loads_restricted(data), np.arange(3, dtype=np.float32))
    # numpy 2 spells the same reconstructor numpy._core.multiarray._reconstruct
    np.testing.assert_array_equal(loads_restricted(data.replace(b"numpy.core.", b"numpy._core.")), np.arange(3))


def test_codecs_encode_only_latin1():
    class _Rot13:
        def __reduce__(self):
            import _codecs

            return (_codecs.encode, ("abc", "rot13"))

    with pytest.raises(pickle.UnpicklingError, match="rot13"):
        loads_restricted(pickle.dumps(_Rot13(), protocol=2))


def test_restricted_pickle_of_plain_arrays_round_trips(tmp_path):
    obj = {"a": np.arange(6, dtype=np.int64).reshape(2, 3), "b": [np.float32(1.5), {"c": np.eye(2)}]}
    path = tmp_path / "x.pkl"
    path.write_bytes(pickle.dumps(obj, protocol=4))
    back = load_restricted_pickle(path)
    np.testing.assert_array_equal(back["a"], obj["a"])
    assert back["b"][0] == np.float32(1.5)
    np.testing.assert_array_equal(back["b"][1]["c"], np.eye(2))
