r"""The toolkit's portable file: a network's declaration as JSON, its numbers as numpy arrays.

:func:`~effect_networks.models.save_npz` writes any network (discrete, continuous,
action parameters and their clusters, declared parent sets, user kinds whose containers
hold tensors) to one ``.npz`` file that numpy and json read without torch::

    net.npz (a zip archive, every member stored uncompressed)
    |- network.json              UTF-8 JSON: format, version, declaration
    |                            (EffectNetwork.to_dict()), pseudo_count, and per site
    |                            its container's saved type and field names
    |- params/<site>/<field>.npy one array per tensor, its dtype and shape as fitted
    '- sha256                    hex sha256 of every other member (see content_sha256)

Reading it without the toolkit::

    import json, numpy as np
    with np.load("net.npz", allow_pickle=False) as z:
        header = json.loads(z["network.json"])            # a member without .npy: bytes
        prior = z["params/action/probs"]                  # (n_actions,) float64

:func:`~effect_networks.models.load_npz` checks what it reads before it builds anything:
the members are stored (none inflates), the JSON is at most :data:`MAX_HEADER_BYTES`, the checksum matches
before the JSON is parsed, the header holds exactly :data:`HEADER_KEYS`, the arrays are
exactly the declared sites' fields, of numeric dtypes, read with ``allow_pickle=False``,
and the numbers fit the declaration's shapes. A round trip keeps every tensor bit for
bit (dtype, shape, NaN payloads, signed zeros).
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from collections.abc import Iterable
from dataclasses import fields
from pathlib import Path

import numpy as np
import torch
from effect_networks.models.cpds import CPD as KindCPD
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.files import stored_members, target_file, write_atomically
from effect_networks.models.params import NetworkParams, check_params, saved_name

PORTABLE_FORMAT = "effect-networks-npz"
PORTABLE_VERSION = 1
#: The keys of ``network.json``; a file whose header holds others is refused.
HEADER_KEYS = frozenset({"format", "version", "declaration", "pseudo_count", "sites"})
#: The largest ``network.json`` that :func:`~effect_networks.models.load_npz` reads.
MAX_HEADER_BYTES = 16 * 2**20
HEADER, CHECKSUM, ARRAYS = "network.json", "sha256", "params/"
#: numpy dtype kinds an array may have: bool, integers, floats, complex numbers.
NUMERIC_KINDS = "biufc"


def save_npz(path: str | Path, net: EffectNetwork, params: NetworkParams) -> Path:
    """Save a fitted network to one portable ``.npz`` file (see the module).

    Written beside ``path`` under a temporary name and renamed over it once complete, so
    a failed save leaves the file that was there. Tensors are saved from the CPU, as
    they are (dtype, shape and bytes).

    Parameters
    ----------
    path
        The file to write (its folder is made if missing).
    net, params
        Any network and its fitted parameters.

    Returns
    -------
    pathlib.Path
        ``path``, as a ``Path``.

    Raises
    ------
    ValueError
        If ``params`` do not fit ``net``, a label of the declaration does not survive
        JSON (``to_dict`` needs JSON scalars), or a container holds other than tensors
        of a numpy dtype.
    """
    check_params(net, params)
    path = target_file(path)
    declaration = net.to_dict()
    kinds = {type(net.cpd(s.name)) for s in net.sites}
    if EffectNetwork.from_dict(json.loads(json.dumps(declaration)), kinds) != net:
        raise ValueError(
            "the declaration does not survive JSON (a label that is not a str, int, float, "
            "bool or None?); give the features JSON scalar labels"
        )
    arrays, sites = {}, {}
    for site, container in params.cpds.items():
        names = [f.name for f in fields(container)]
        sites[site] = {"type": saved_name(type(container)), "fields": names}
        for name in names:
            arrays[f"{ARRAYS}{site}/{name}.npy"] = _array(site, name, getattr(container, name))
    header = {
        "format": PORTABLE_FORMAT,
        "version": PORTABLE_VERSION,
        "declaration": declaration,
        "pseudo_count": float(params.pseudo_count),
        "sites": sites,
    }
    members = {HEADER: json.dumps(header, allow_nan=False, indent=1).encode()}
    for name, array in arrays.items():
        buffer = io.BytesIO()
        np.lib.format.write_array(buffer, array, allow_pickle=False)
        members[name] = buffer.getvalue()
    members[CHECKSUM] = content_sha256(members).encode()
    content = io.BytesIO()
    with zipfile.ZipFile(content, "w", zipfile.ZIP_STORED) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return write_atomically(path, content.getbuffer())


def load_npz(
    path: str | Path, kinds: Iterable[type[KindCPD]] = ()
) -> tuple[EffectNetwork, NetworkParams]:
    """Load a network saved by :func:`~effect_networks.models.save_npz`, checking it first.

    Parameters
    ----------
    path
        A file written by :func:`~effect_networks.models.save_npz`.
    kinds
        The classes of the user-defined kinds it names (the toolkit's own are known).

    Returns
    -------
    tuple of EffectNetwork and NetworkParams
        The declaration and the parameters, the same numbers bit for bit.

    Raises
    ------
    ValueError
        Naming the file and what is wrong: not a zip of stored members, a member of
        another name, a header too large, a checksum that differs (a changed byte),
        another format or version, unknown header keys, arrays missing or extra, of a
        non-numeric dtype or of the wrong shape.
    """
    path = Path(path)
    what = "portable effect-network file (.npz)"
    members = {m.filename: m for m in stored_members(path, what)}
    for name in members:
        if name not in (HEADER, CHECKSUM) and not (
            name.startswith(ARRAYS) and name.endswith(".npy")
        ):
            raise ValueError(
                f"{path} holds an unknown member {name!r}; a portable file holds {HEADER!r}, "
                f"{CHECKSUM!r} and {ARRAYS}<site>/<field>.npy arrays only"
            )
    for name in (HEADER, CHECKSUM):
        if name not in members:
            raise ValueError(f"{path} is not a {what}: it has no {name!r} member")
    if members[HEADER].file_size > MAX_HEADER_BYTES:
        raise ValueError(
            f"{path}: its {HEADER!r} has {members[HEADER].file_size} bytes, more than "
            f"MAX_HEADER_BYTES = {MAX_HEADER_BYTES}; refused unread"
        )
    try:
        with zipfile.ZipFile(path) as archive:
            content = {name: archive.read(name) for name in members}
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, NotImplementedError) as exc:
        raise ValueError(f"{path} is a damaged {what} ({type(exc).__name__}: {exc})") from exc
    saved = content.pop(CHECKSUM)
    if saved != content_sha256(content).encode():
        raise ValueError(
            f"{path} is damaged: its content does not match the sha256 checksum saved with it "
            "(a changed byte); re-save the network from its source"
        )
    try:
        header = json.loads(content.pop(HEADER).decode())
        net, params = _build(header, content, kinds)
    except (KeyError, TypeError, ValueError, AttributeError, RecursionError) as exc:
        raise ValueError(f"{path} is a damaged {what} ({type(exc).__name__}: {exc})") from exc
    return net, params


def content_sha256(members: dict[str, bytes]) -> str:
    """sha256 of a portable file's members other than ``sha256``, in sorted name order.

    Each member contributes its name's UTF-8 bytes, a NUL byte, its length as 8
    little-endian bytes and its bytes (an ``.npy`` member's bytes include its header:
    dtype and shape).
    """
    h = hashlib.sha256()
    for name in sorted(members):
        if name == CHECKSUM:
            continue
        data = members[name]
        h.update(name.encode() + b"\0" + len(data).to_bytes(8, "little"))
        h.update(data)
    return h.hexdigest()


def _array(site: str, name: str, value: object) -> np.ndarray:
    if not isinstance(value, torch.Tensor):
        raise ValueError(
            f"site {site!r}: its {name!r} is a {type(value).__name__}; a portable file holds "
            "tensors only (save the network with models.save)"
        )
    try:
        array = value.detach().cpu().resolve_conj().resolve_neg().numpy()
    except TypeError as exc:  # a dtype numpy lacks (bfloat16, ...)
        raise ValueError(
            f"site {site!r}: its {name!r} has dtype {value.dtype}, which numpy cannot hold; "
            "convert it (params.map) or save the network with models.save"
        ) from exc
    return np.array(array, order="C", copy=True)  # ascontiguousarray would make 0-d 1-d


def _build(header, content: dict[str, bytes], kinds) -> tuple[EffectNetwork, NetworkParams]:
    """The network and parameters of a verified file's header and array members."""
    if not isinstance(header, dict) or header.get("format") != PORTABLE_FORMAT:
        raise ValueError(f"no {PORTABLE_FORMAT!r} header")
    if header.get("version") != PORTABLE_VERSION:
        raise ValueError(
            f"format version {header.get('version')!r}; this toolkit reads version "
            f"{PORTABLE_VERSION}"
        )
    if set(header) != HEADER_KEYS:
        raise ValueError(f"header keys {sorted(header)}; expected {sorted(HEADER_KEYS)}")
    pseudo_count = header["pseudo_count"]
    if not isinstance(pseudo_count, int | float) or isinstance(pseudo_count, bool):
        raise ValueError(f"pseudo_count {pseudo_count!r} is not a number")
    net = EffectNetwork.from_dict(header["declaration"], kinds)
    sites = header["sites"]
    declared = [s.name for s in net.sites]
    if sorted(sites) != sorted(declared):
        raise ValueError(f"the file's sites {sorted(sites)} are not the network's {declared}")
    expected = set()
    cpds = {}
    for site in declared:
        cls = net.cpd(site).params_type
        entry = sites[site]
        if entry["type"] != saved_name(cls):
            raise ValueError(f"site {site!r} holds no {cls.__name__} ({saved_name(cls)!r})")
        names = [f.name for f in fields(cls)]
        if sorted(entry["fields"]) != sorted(names):
            raise ValueError(
                f"site {site!r}: its {cls.__name__} holds {sorted(entry['fields'])}, "
                f"expected {sorted(names)}"
            )
        values = {}
        for name in names:
            member = f"{ARRAYS}{site}/{name}.npy"
            expected.add(member)
            if member not in content:
                raise ValueError(f"site {site!r}: no array {member!r}")
            array = np.lib.format.read_array(io.BytesIO(content[member]), allow_pickle=False)
            if array.dtype.kind not in NUMERIC_KINDS or array.dtype.byteorder == ">":
                raise ValueError(f"{member!r} has dtype {array.dtype}; expected a numeric one")
            values[name] = torch.from_numpy(array.copy())  # writable, the same bytes
        cpds[site] = cls(**values)
    extra = sorted(set(content) - expected)
    if extra:
        raise ValueError(f"arrays {extra} belong to no site's container")
    params = NetworkParams(cpds, float(pseudo_count), net)
    check_params(net, params)
    return net, params
