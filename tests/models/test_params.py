"""Parameters bound to their declaration, and model files: checked, atomic, not inflated."""

import collections
import errno
import io
import json
import pickle
import random
import zipfile

import numpy as np
import pytest
import torch
from effect_networks.inference import fit, fit_gradient, infer_action, predict
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    effect_model,
    load,
    save,
)
from effect_networks.models.params import NetworkParams, _checksum, check_params, random_params
from hypothesis import given, settings
from hypothesis import strategies as st
from pyro import poutine

from tests.helpers import fill_the_disk


def visible_network(states, *, kind="object", actions=("look", "remove")):
    return EffectNetwork((Discrete("visible", states, kind=kind),), actions)


def visible_rows(n=200, seed=0):
    """Rows where "remove" makes the object invisible and "look" changes nothing."""
    rng = np.random.default_rng(seed)
    action = rng.choice(["look", "remove"], n)
    visible = rng.random(n) < 0.7
    return {
        "initial.visible": visible,
        "action": action,
        "end.visible": visible & (action != "remove"),
    }


# ------------------------------------------------------------------ A6: bound parameters
def test_parameters_fitted_for_other_state_order_are_refused_everywhere(tmp_path):
    fitted_for = visible_network((False, True))
    other = visible_network((True, False))
    params = fit(fitted_for, visible_rows()).params
    ev = {"initial.visible": [True], "action": ["remove"]}
    # with its own declaration, "remove" leaves the object invisible
    assert float(predict(fitted_for, params, ev).prob("visible", False)[0]) > 0.99
    match = (
        r"site 'initial.visible': .*fitted for states \(False, True\).*has states \(True, False\)"
    )
    with pytest.raises(ValueError, match=match):
        predict(other, params, ev)
    with pytest.raises(ValueError, match=match):
        infer_action(other, params, {"initial.visible": [True], "end.visible": [False]})
    with pytest.raises(ValueError, match=match):
        save(tmp_path / "net.pt", other, params)
    with pytest.raises(ValueError, match=match):
        poutine.trace(effect_model).get_trace(other, params, {"initial.visible": [True]})
    with pytest.raises(ValueError, match=match):
        fit_gradient(other, visible_rows(), init=params)
    assert not (tmp_path / "net.pt").exists()


@pytest.mark.parametrize(
    ("other", "site", "what"),
    [
        (visible_network((0, 1)), "initial.visible", "state types"),
        (visible_network((False, True), actions=("remove", "look")), "action", "actions"),
        (
            EffectNetwork(
                (Discrete("visible", (False, True)),),
                ("look", "remove"),
                parents={"end.visible": ("action",)},
            ),
            "end.visible",
            "discrete parents",
        ),
    ],
)
def test_a_declaration_with_another_identity_is_named(other, site, what):
    params = random_params(visible_network((False, True)), 0)
    with pytest.raises(ValueError, match=rf"site '{site}': the parameters were fitted for {what}"):
        check_params(other, params)


@settings(max_examples=40, deadline=None)
@given(st.permutations(("a", "b", "c")), st.permutations(("x", "y", "z")), st.booleans())
def test_parameters_are_refused_by_any_reordering_of_states_or_actions(states, actions, tied):
    def net(states, actions, using):
        return EffectNetwork(
            (Discrete("f", tuple(states)), Continuous("pos")),
            tuple(actions),
            (Parameter("p", 0.0, 1.0, 2, using if tied else ("x",), "pos"),),
        )

    params = random_params(net(("a", "b", "c"), ("x", "y", "z"), ("x", "y")), 0)
    other = net(states, actions, ("y", "x"))
    if tuple(states) != ("a", "b", "c"):
        with pytest.raises(ValueError, match=r"site 'initial.f': .*states \('a', 'b', 'c'\)"):
            check_params(other, params)
    elif tuple(actions) != ("x", "y", "z"):
        with pytest.raises(ValueError, match=r"site 'action': .*actions \('x', 'y', 'z'\)"):
            check_params(other, params)
    else:  # the same declaration: the order the parameter names its actions in is no matter
        check_params(other, params)


def test_parameter_layout_and_range_are_part_of_the_identity():
    def net(**kw):
        p = dict(name="force", low=0.0, high=10.0, bins=4, actions=("tap",), affects="x") | kw
        return EffectNetwork((Continuous("x"),), ("tap", "wait"), (Parameter(**p),))

    params = random_params(net(), 0)
    check_params(net(), params)  # an equal declaration, another object
    with pytest.raises(ValueError, match=r"site 'cluster.force'.* layout 'grid'.* 'adaptive'"):
        check_params(net(layout="adaptive"), params)
    with pytest.raises(ValueError, match=r"site 'cluster.force'.* range"):
        check_params(net(high=20.0), params)


def test_what_does_not_change_the_numbers_meaning_is_accepted(tmp_path):
    params = fit(visible_network((False, True)), visible_rows()).params
    # a feature's kind is metadata; a loaded declaration is another, equal, object
    check_params(visible_network((False, True), kind="world"), params)
    net2, params2 = load(save(tmp_path / "net.pt", visible_network((False, True)), params))
    assert params2.network is net2
    check_params(visible_network((False, True)), params2)
    # parameters assembled by hand carry no declaration: checked by shape only
    check_params(visible_network((True, False)), NetworkParams(params.cpds, params.pseudo_count))
    # map keeps the binding
    with pytest.raises(ValueError, match="states"):
        check_params(visible_network((True, False)), params.map(lambda t: t.clone()))


# ------------------------------------------------------------------ A7: content checksum
NET = EffectNetwork(
    (Discrete("visible", (False, True)), Continuous("pos", 2)),
    ("remove", "tap"),
    (Parameter("force", (0.0,), (10.0,), (4,), ("tap",), "pos"),),
)


def same_numbers(a: NetworkParams, b: NetworkParams) -> bool:
    return a.pseudo_count == b.pseudo_count and all(
        torch.equal(getattr(a[s], f), getattr(b[s], f))
        for s in a.cpds
        for f in a[s].__dataclass_fields__
    )


def member_spans(data: bytes) -> list[range]:
    """The byte ranges of a zip's members' contents."""
    spans = []
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        for m in z.infolist():
            header = data[m.header_offset : m.header_offset + 30]  # the local file header
            name_len = int.from_bytes(header[26:28], "little")
            extra_len = int.from_bytes(header[28:30], "little")
            start = m.header_offset + 30 + name_len + extra_len
            spans.append(range(start, start + m.compress_size))
    return spans


def test_a_flipped_bit_never_loads_as_other_numbers(tmp_path):
    params = random_params(NET, 3)
    good = save(tmp_path / "net.pt", NET, params).read_bytes()
    rng = random.Random(0)
    # every member's content (numbers, structure) densely, the rest of the file sparsely
    inside = [i for span in member_spans(good) for i in span]
    positions = rng.sample(inside, 250) + rng.sample(range(len(good)), 50)
    loaded = 0
    bad = tmp_path / "flipped.pt"
    for i in positions:
        flipped = bytearray(good)
        flipped[i] ^= 1 << rng.randrange(8)
        bad.write_bytes(bytes(flipped))
        try:
            net2, params2 = load(bad)
        except ValueError:
            continue
        loaded += 1
        assert net2 == NET and same_numbers(params2, params), f"bit flip at byte {i}"
    assert loaded < len(positions) // 2  # most flips are caught, not harmless


# ------------------------------------------------------------------ B9: atomic save
def test_a_failed_save_leaves_the_previous_file(tmp_path, monkeypatch):
    old = random_params(NET, 1)
    path = save(tmp_path / "net.pt", NET, old)
    real_save = torch.save

    def disk_full(obj, f, *args, **kwargs):
        buffer = io.BytesIO()
        real_save(obj, buffer)
        part = buffer.getvalue()[:300]
        if hasattr(f, "write"):
            f.write(part)
        else:
            with open(f, "wb") as out:
                out.write(part)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", disk_full)
    with pytest.raises(OSError, match="No space left"):
        save(path, NET, random_params(NET, 2))
    monkeypatch.undo()
    net2, params2 = load(path)
    assert net2 == NET and same_numbers(params2, old)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["net.pt"]  # no temporary left
    new = random_params(NET, 2)
    save(path, NET, new)
    assert same_numbers(load(path)[1], new)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["net.pt"]


# ------------------------------------------------------------------ B11: unknown payloads
_STORAGES = {
    torch.float64: torch.DoubleStorage,
    torch.float32: torch.FloatStorage,
    torch.int64: torch.LongStorage,
    torch.bool: torch.BoolStorage,
}


class _Storage:
    def __init__(self, key, dtype, numel):
        self.key, self.dtype, self.numel = key, dtype, numel


class _Tensor:
    def __init__(self, storage, shape):
        self.storage, self.shape = storage, tuple(shape)

    def __reduce__(self):
        stride = tuple(int(np.prod(self.shape[i + 1 :])) for i in range(len(self.shape)))
        args = (self.storage, 0, self.shape, stride, False, collections.OrderedDict())
        return (torch._utils._rebuild_tensor_v2, args)


class _Pickler(pickle.Pickler):
    def persistent_id(self, obj):
        if isinstance(obj, _Storage):
            return ("storage", _STORAGES[obj.dtype], obj.key, "cpu", obj.numel)
        return None


def with_hidden_tensor(valid, out, numel):
    """``valid``'s payload plus an entry ``extra``: ``numel`` float32 zeros stored as a
    deflated zip member, written as torch's zip format lays a file out, in chunks (the
    test never holds the tensor)."""
    members = {}

    def refs(x):
        if isinstance(x, torch.Tensor):
            key = str(len(members))
            members[key] = x.contiguous().numpy().tobytes()
            return _Tensor(_Storage(key, x.dtype, x.numel()), x.shape)
        if isinstance(x, dict):
            return {k: refs(v) for k, v in x.items()}
        return x

    payload = refs(torch.load(valid, weights_only=True))
    hidden = str(len(members))
    payload["extra"] = _Tensor(_Storage(hidden, torch.float32, numel), (numel,))
    structure = io.BytesIO()
    _Pickler(structure, protocol=2).dump(payload)
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        stored = zipfile.ZIP_STORED
        z.writestr("archive/data.pkl", structure.getvalue(), compress_type=stored)
        z.writestr("archive/byteorder", "little", compress_type=stored)
        z.writestr("archive/version", "3\n", compress_type=stored)
        for key, data in members.items():
            z.writestr(f"archive/data/{key}", data, compress_type=stored)
        with z.open(f"archive/data/{hidden}", "w", force_zip64=True) as f:
            chunk = bytes(2**24)
            for _ in range(numel * 4 // len(chunk)):
                f.write(chunk)


def test_a_deflated_gigabyte_under_an_unknown_key_is_refused_unread(tmp_path, monkeypatch):
    valid = save(tmp_path / "net.pt", NET, random_params(NET, 0))
    bomb = tmp_path / "bomb.pt"
    with_hidden_tensor(valid, bomb, 2**28)  # 1 GiB of float32 zeros
    assert bomb.stat().st_size < 8 * 2**20
    calls = []
    real_load = torch.load
    monkeypatch.setattr(torch, "load", lambda *a, **k: calls.append(a) or real_load(*a, **k))
    with pytest.raises(ValueError, match=r"member 'archive/data/\d+' is compressed \(1073741824"):
        load(bomb)
    assert calls == []  # refused before torch read anything


def test_an_unknown_entry_is_refused(tmp_path):
    valid = save(tmp_path / "net.pt", NET, random_params(NET, 0))
    payload = torch.load(valid, weights_only=True)
    torch.save(payload | {"extra": torch.zeros(1000)}, tmp_path / "extra.pt")
    with pytest.raises(ValueError, match=r"holds unknown entries \['extra'\]"):
        load(tmp_path / "extra.pt")
    entry = payload["cpds"]["end.pos"]
    spare = payload | {"cpds": payload["cpds"] | {"end.pos": entry | {"spare": torch.zeros(9)}}}
    torch.save(spare, tmp_path / "spare.pt")
    with pytest.raises(ValueError, match="does not match the sha256 checksum"):
        load(tmp_path / "spare.pt")
    torch.save(spare | {"sha256": _checksum(spare)}, tmp_path / "spare.pt")  # resealed
    with pytest.raises(ValueError, match=r"site 'end.pos': its LinearGaussianParams holds"):
        load(tmp_path / "spare.pt")


# ------------------------------------------------ files saved before the containers' rename
#: A file's payload as the toolkit wrote it while the containers were named ``Table``,
#: ``Softmax`` and ``LinearGaussian`` (format 2): every kind once, fixed numbers, and the
#: checksum that toolkit's ``save`` wrote for them.
OLD_DECLARATION = (
    '{"features": [{"type": "discrete", "name": "door", "states": ["shut", "open"], '
    '"kind": "object", "initial": true}, {"type": "continuous", "name": "x", "dim": 1, '
    '"kind": "object", "initial": true}], "actions": ["push", "wait"], "parameters": []}'
)
OLD_SHA256 = "cddc2f5b99d129d8cf0e64324269d400a1cd412eb3b865725576dbe1e4294401"


def old_cpds() -> dict:
    def f64(v):
        return torch.tensor(v, dtype=torch.float64)

    return {
        "initial.door": {"type": "Table", "probs": f64([0.25, 0.75]), "n": f64(4.0)},
        "initial.x": {
            "type": "LinearGaussian",
            "weight": torch.zeros(1, 0, dtype=torch.float64),
            "bias": f64([0.5]),
            "scale_tril": f64([[2.0]]),
            "n": f64(4.0),
        },
        "action": {"type": "Table", "probs": f64([0.5, 0.5]), "n": f64(4.0)},
        "end.door": {
            "type": "Softmax",
            "weight": f64([[[[1.0], [-1.0]], [[0.0], [0.0]]], [[[0.5], [0.0]], [[0.0], [2.0]]]]),
            "bias": f64([[[0.0, 1.0], [1.0, 0.0]], [[0.0, 0.0], [0.5, 0.5]]]),
            "n": f64([[1.0, 1.0], [1.0, 1.0]]),
        },
        "end.x": {
            "type": "LinearGaussian",
            "weight": f64([[[[1.0]], [[0.0]]], [[[2.0]], [[1.0]]]]),
            "bias": f64([[[0.0], [1.0]], [[2.0], [3.0]]]),
            "scale_tril": f64([[[[1.0]], [[1.0]]], [[[0.5]], [[0.5]]]]),
            "n": f64([[1.0, 1.0], [1.0, 1.0]]),
        },
    }


def test_a_file_saved_before_the_rename_loads_and_saves_alike(tmp_path):
    from effect_networks.models.cpds import LinearGaussianParams, SoftmaxParams, TableParams

    payload = {
        "format": "effect-networks",
        "version": 2,
        "declaration": OLD_DECLARATION,
        "pseudo_count": 0.5,
        "cpds": old_cpds(),
        "sha256": OLD_SHA256,
    }
    torch.save(payload, tmp_path / "old.pt")
    net, params = load(tmp_path / "old.pt")
    kinds = {"Table": TableParams, "Softmax": SoftmaxParams, "LinearGaussian": LinearGaussianParams}
    for site, entry in old_cpds().items():
        assert type(params[site]) is kinds[entry.pop("type")]
        for name, value in entry.items():
            assert torch.equal(getattr(params[site], name), value), (site, name)
    # saved again, the file holds the same payload: the same names and checksum
    again = torch.load(save(tmp_path / "again.pt", net, params), weights_only=True)
    assert {s: e["type"] for s, e in again["cpds"].items()} == {
        s: e["type"] for s, e in payload["cpds"].items()
    }
    assert again["sha256"] == OLD_SHA256


def test_the_checksum_is_verified_before_the_declaration_is_parsed(tmp_path, monkeypatch):
    valid = save(tmp_path / "net.pt", NET, random_params(NET, 0))
    payload = torch.load(valid, weights_only=True)
    deep = "[" * 100_000 + "]" * 100_000  # deeper than json.loads can recurse
    torch.save(payload | {"declaration": deep}, tmp_path / "deep.pt")
    parsed = []
    monkeypatch.setattr(json, "loads", lambda *a, **k: parsed.append(a) or {})
    with pytest.raises(ValueError, match="does not match the sha256 checksum"):
        load(tmp_path / "deep.pt")
    assert parsed == []  # refused before anything in it was parsed
    monkeypatch.undo()
    resealed = payload | {"declaration": deep}
    torch.save(resealed | {"sha256": _checksum(resealed)}, tmp_path / "deep.pt")
    with pytest.raises(ValueError, match="damaged effect-network file .*RecursionError"):
        load(tmp_path / "deep.pt")


def test_a_disk_that_fills_during_save_is_an_oserror_naming_the_file(tmp_path, monkeypatch):
    """Wherever the disk fills, save raises OSError(ENOSPC) naming the file, and the
    previous file stays whole."""
    old = random_params(NET, 1)
    path = save(tmp_path / "net.pt", NET, old)
    fill_the_disk(monkeypatch)
    with pytest.raises(OSError, match=r"No space left on device: cannot save .*net\.pt") as caught:
        save(path, NET, random_params(NET, 2))
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(path)
    monkeypatch.undo()
    net2, params2 = load(path)
    assert net2 == NET and same_numbers(params2, old)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["net.pt"]
