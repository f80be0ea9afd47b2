"""Old names answer for one release, with a DeprecationWarning naming the new one."""

import importlib
import warnings

import pytest

from models.deprecation import renamed

#: Where each old container name was importable, and its new name there.
OLD = [
    (module, old, f"{old}Params")
    for module in ("models", "models.cpds", "models.params")
    for old in ("Table", "Softmax", "LinearGaussian")
] + [
    ("models.cpds.table", "Table", "TableParams"),
    ("models.cpds.softmax", "Softmax", "SoftmaxParams"),
    ("models.cpds.linear_gaussian", "LinearGaussian", "LinearGaussianParams"),
    ("models.params", "CPD", "SiteParams"),
]


@pytest.mark.parametrize("module, old, new", OLD, ids=str)
def test_an_old_name_is_the_new_object_with_a_warning(module, old, new):
    m = importlib.import_module(module)
    with pytest.warns(DeprecationWarning, match=rf"{module}\.{old} is now {module}\.{new}"):
        value = getattr(m, old)
    assert value is getattr(m, new)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        getattr(m, new)  # the new name warns nothing


def test_from_import_of_an_old_name_warns_at_the_importer():
    with pytest.warns(DeprecationWarning) as record:
        from models.cpds import Table  # noqa: F401
    assert record[0].filename == __file__


def test_an_unknown_name_is_an_attribute_error():
    fallback = renamed("models.cpds", {"Table": "TableParams"})
    with pytest.raises(AttributeError, match="module 'models.cpds' has no attribute 'Tabel'"):
        fallback("Tabel")
    with pytest.raises(AttributeError):
        importlib.import_module("models").Tabel  # noqa: B018


def test_the_can_networks_count_function_is_n_cans():
    import numpy as np

    from models import can_network

    masks = np.array([[0, 1], [0b1011, 1023]])
    assert can_network.n_cans(masks).tolist() == [[0, 1], [3, 10]]
    with pytest.warns(DeprecationWarning, match="n_cans"):
        old = can_network.count
    assert old is can_network.n_cans
