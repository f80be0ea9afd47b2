"""The portable file (models.portable): every network round-trips bit for bit, json and
numpy alone read every number, and a damaged or crafted file is refused before anything
is built from it."""

import hashlib
import io
import json
import random
import zipfile
from dataclasses import fields

import numpy as np
import pytest
import torch
from effect_networks.inference import fit, simulate
from effect_networks.models import (
    EffectNetwork,
    NetworkParams,
    TableCPD,
    load,
    load_npz,
    random_params,
    save,
    save_npz,
)
from effect_networks.models.portable import HEADER_KEYS, content_sha256
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.helpers import fill_the_disk
from tests.networks import (
    NET,
    README_NET,
    declared_networks,
    networks_of_every_kind,
    same_bits,
)


class Counted(TableCPD):
    """A kind of the user's (its numbers are a table's)."""

    name = "counted"


def assert_same(net, params, back_net, back):
    assert back_net == net
    assert back.pseudo_count == params.pseudo_count
    assert list(back.cpds) == list(params.cpds)
    for site, cpd in params.cpds.items():
        assert type(back[site]) is type(cpd), site
        for name in (f.name for f in fields(cpd)):
            assert same_bits(getattr(cpd, name).detach(), getattr(back[site], name)), (site, name)


ROUNDTRIP = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@ROUNDTRIP
@given(net=networks_of_every_kind(), seed=st.integers(0, 2**16), unseen=st.sampled_from([0, 0.4]))
def test_every_kind_of_network_round_trips_bit_for_bit(tmp_path_factory, net, seed, unseen):
    params = random_params(net, seed, unseen=unseen)
    path = save_npz(tmp_path_factory.mktemp("npz") / "net.npz", net, params)
    assert_same(net, params, *load_npz(path))


@ROUNDTRIP
@given(net=declared_networks(), seed=st.integers(0, 2**16))
def test_declared_discrete_networks_round_trip_bit_for_bit(tmp_path_factory, net, seed):
    params = random_params(net, seed, unseen=0.3)
    path = save_npz(tmp_path_factory.mktemp("npz") / "net.npz", net, params)
    assert_same(net, params, *load_npz(path))


def test_a_fitted_network_with_a_parameter_and_odd_numbers_round_trips(tmp_path):
    params = fit(README_NET, simulate(README_NET, random_params(README_NET, 1), 300, seed=1)).params
    assert_same(README_NET, params, *load_npz(save_npz(tmp_path / "net.npz", README_NET, params)))
    # NaN payloads, signed zeros, subnormals, float32 and a strided view keep their bits
    table, visible = params["action"], params["initial.visible"].probs
    nan = torch.tensor([0x7FF8DEADBEEF0001], dtype=torch.int64).view(torch.float64)[0]
    strided = torch.stack([visible, visible], -1)[..., 1]  # a view, not contiguous
    cpds = dict(params.cpds)
    cpds["action"] = type(table)(table.probs.float(), torch.tensor(-0.0, dtype=torch.float64))
    cpds["initial.visible"] = type(table)(strided, nan)
    cpds["cluster.force"] = type(table)(
        params["cluster.force"].probs, params["cluster.force"].n * 5e-324
    )
    odd_params = NetworkParams(cpds, 0.0, README_NET)
    path = save_npz(tmp_path / "odd.npz", README_NET, odd_params)
    assert_same(README_NET, odd_params, *load_npz(path))


def test_a_user_kind_round_trips_when_named(tmp_path):
    net = EffectNetwork(
        NET.features, NET.actions, NET.parameters, kinds={"initial.visible": Counted}
    )
    params = random_params(net, 4)
    path = save_npz(tmp_path / "net.npz", net, params)
    assert_same(net, params, *load_npz(path, kinds=(Counted,)))
    with pytest.raises(ValueError, match="kind 'counted'.*kinds="):
        load_npz(path)


def test_json_and_numpy_alone_find_every_number(tmp_path):
    params = random_params(README_NET, 2)
    path = save_npz(tmp_path / "net.npz", README_NET, params)
    with np.load(path, allow_pickle=False) as z:
        header = json.loads(z["network.json"])
        arrays = {name: z[name] for name in z.files if name.startswith("params/")}
    assert set(header) == HEADER_KEYS and header["declaration"] == README_NET.to_dict()
    assert header["pseudo_count"] == params.pseudo_count
    found = set()
    for site, entry in header["sites"].items():
        for name in entry["fields"]:
            array, tensor = arrays[f"params/{site}/{name}"], getattr(params[site], name)
            assert array.dtype == tensor.numpy().dtype and array.shape == tuple(tensor.shape)
            assert array.tobytes() == tensor.contiguous().numpy().tobytes(), (site, name)
            found.add(f"params/{site}/{name}")
    assert found == set(arrays) and {s.name for s in README_NET.sites} == set(header["sites"])
    # the checksum, by zipfile and hashlib alone
    with zipfile.ZipFile(path) as archive:
        members = {m: archive.read(m) for m in archive.namelist()}
    h = hashlib.sha256()
    for name in sorted(set(members) - {"sha256"}):
        h.update(name.encode() + b"\0" + len(members[name]).to_bytes(8, "little") + members[name])
    assert members["sha256"].decode() == h.hexdigest()


# ------------------------------------------------------------------ damaged and crafted files
def members_of(path):
    with zipfile.ZipFile(path) as archive:
        return {m: archive.read(m) for m in archive.namelist()}


def reseal(members, out, compress=zipfile.ZIP_STORED):
    """Write ``members`` as a portable file with a fresh, valid checksum."""
    members = dict(members)
    members["sha256"] = content_sha256(members).encode()
    with zipfile.ZipFile(out, "w", compress) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return out


@pytest.fixture
def saved(tmp_path):
    params = random_params(NET, 3)
    return save_npz(tmp_path / "net.npz", NET, params), params


def test_a_flipped_bit_never_loads_as_other_numbers(saved, tmp_path):
    path, params = saved
    good = path.read_bytes()
    rng = random.Random(0)
    bad = tmp_path / "flipped.npz"
    loaded = 0
    for i in rng.sample(range(len(good)), 300):
        flipped = bytearray(good)
        flipped[i] ^= 1 << rng.randrange(8)
        bad.write_bytes(bytes(flipped))
        try:
            net2, params2 = load_npz(bad)
        except ValueError:
            continue
        loaded += 1  # a flip in the zip's bookkeeping that changes no content
        assert_same(NET, params, net2, params2)
    assert loaded < 150


def test_a_changed_number_is_refused_by_the_checksum(saved, tmp_path):
    path, _ = saved
    members = members_of(path)
    name = "params/end.pos/bias.npy"
    members[name] = members[name][:-1] + bytes([members[name][-1] ^ 1])
    with zipfile.ZipFile(tmp_path / "bad.npz", "w") as archive:
        for member, data in members.items():
            archive.writestr(member, data)
    with pytest.raises(ValueError, match="does not match the sha256 checksum"):
        load_npz(tmp_path / "bad.npz")


def test_the_checksum_is_verified_before_the_header_is_parsed(saved, tmp_path, monkeypatch):
    path, _ = saved
    members = members_of(path)
    members["network.json"] = members["network.json"].replace(b'"push"', b'"pull"')
    with zipfile.ZipFile(tmp_path / "bad.npz", "w") as archive:
        for member, data in members.items():
            archive.writestr(member, data)
    parsed = []
    real = json.loads
    monkeypatch.setattr(json, "loads", lambda *a, **k: parsed.append(a) or real(*a, **k))
    with pytest.raises(ValueError, match="checksum"):
        load_npz(tmp_path / "bad.npz")
    assert parsed == []


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda m: m.pop("params/end.pos/bias.npy"), "no array 'params/end.pos/bias.npy'"),
        (lambda m: m.update({"params/end.pos/extra.npy": m["params/end.pos/n.npy"]}), "extra"),
        (lambda m: m.update({"notes.txt": b"hello"}), "unknown member 'notes.txt'"),
        (lambda m: m.pop("network.json"), "no 'network.json' member"),
        (lambda m: m.update({"network.json": b"{not json"}), "damaged.*JSONDecodeError"),
        (
            lambda m: m.update(
                {"network.json": m["network.json"].replace(b'"version": 1', b'"version": 9')}
            ),
            "format version 9",
        ),
        (
            lambda m: m.update({"network.json": m["network.json"].replace(b'"sites"', b'"other"')}),
            "header keys",
        ),
    ],
)
def test_a_resealed_file_of_another_layout_is_refused(saved, tmp_path, change, message):
    path, _ = saved
    members = members_of(path)
    members.pop("sha256")
    change(members)
    with pytest.raises(ValueError, match=message):
        load_npz(reseal(members, tmp_path / "crafted.npz"))


def array_bytes(array, allow_pickle=False):
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, array, allow_pickle=allow_pickle)
    return buffer.getvalue()


@pytest.mark.parametrize(
    ("array", "message"),
    [
        (np.array([None, 1.0], dtype=object), "Object arrays cannot be loaded"),
        (np.array(["a", "b"]), "dtype <U1"),
        (np.zeros((5, 5)), "shape"),
    ],
)
def test_an_array_that_is_no_number_of_the_declared_shape_is_refused(
    saved, tmp_path, array, message
):
    path, _ = saved
    members = members_of(path)
    members.pop("sha256")
    members["params/end.pos/n.npy"] = array_bytes(array, allow_pickle=True)
    with pytest.raises(ValueError, match=message):
        load_npz(reseal(members, tmp_path / "crafted.npz"))


def test_a_compressed_member_is_refused_unread(saved, tmp_path):
    path, _ = saved
    members = members_of(path)
    members.pop("sha256")
    crafted = reseal(members, tmp_path / "deflated.npz", zipfile.ZIP_DEFLATED)
    with pytest.raises(ValueError, match="is compressed"):
        load_npz(crafted)


@pytest.mark.parametrize("fmt", ["npz", "pt"])
def test_a_member_marked_encrypted_is_refused_unread(saved, tmp_path, fmt):
    """Every entry's encryption flag set in turn: a ValueError (zipfile raised RuntimeError)."""
    path = saved[0] if fmt == "npz" else save(tmp_path / "net.pt", NET, saved[1])
    read = load_npz if fmt == "npz" else load
    good = path.read_bytes()
    entries = [i for i in range(len(good)) if good.startswith(b"PK\x01\x02", i)]
    assert entries
    for entry in entries:
        flagged = bytearray(good)
        flagged[entry + 8] |= 0x1  # the central directory's general-purpose flag: encrypted
        (tmp_path / f"flagged.{fmt}").write_bytes(bytes(flagged))
        with pytest.raises(ValueError, match="marked encrypted"):
            read(tmp_path / f"flagged.{fmt}")


def test_not_a_zip_and_a_truncated_file_are_refused(saved, tmp_path):
    path, _ = saved
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(ValueError, match="not a readable portable effect-network file"):
        load_npz(tmp_path / "text.npz")
    (tmp_path / "short.npz").write_bytes(path.read_bytes()[:-200])
    with pytest.raises(ValueError):
        load_npz(tmp_path / "short.npz")


def test_a_failed_save_leaves_the_previous_file(saved, monkeypatch):
    path, old = saved
    fill_the_disk(monkeypatch)
    with pytest.raises(OSError, match=r"No space left on device: cannot save .*net\.npz"):
        save_npz(path, NET, random_params(NET, 9))
    monkeypatch.undo()
    assert_same(NET, old, *load_npz(path))
    assert sorted(p.name for p in path.parent.iterdir()) == ["net.npz"]  # no temporary left


def test_what_numpy_cannot_hold_is_refused_at_save(tmp_path):
    params = random_params(NET, 0)
    with pytest.raises(
        ValueError, match="site 'initial.visible': its 'probs' has dtype torch.bfloat16"
    ):
        save_npz(tmp_path / "net.npz", NET, params.map(lambda t: t.to(torch.bfloat16)))
    with pytest.raises(ValueError, match="is a folder"):
        save_npz(tmp_path, NET, params)
