"""One way in for training rows (inference.fitting.reading.read_rows): every function that
takes rows reads a mapping, a DataFrame with gaps and a CSV round trip alike.

README's frame with gaps (None in a discrete column, NaN in a continuous one) is taken by
every entry point; a property test draws small networks and rows and checks that each
entry point gives the same answer for the rows as a dict (gaps as NaN and masks), as a
DataFrame, and as a DataFrame written to CSV and read back.
"""

import dataclasses
import io

import numpy as np
import pandas as pd
import pytest
import torch
from effect_networks.inference import (
    aic,
    bic,
    cross_validate,
    fit,
    fit_em,
    learn_structure,
    log_likelihood,
    select_clusters,
    simulate,
)
from effect_networks.inference.fitting.reading import read_rows
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    Partial,
    random_params,
    to_frame,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

pytestmark = [
    pytest.mark.filterwarnings("ignore::effect_networks.inference.ConvergenceWarning"),
    pytest.mark.filterwarnings("ignore::effect_networks.inference.OutsideTrainingData"),
]

README_NET = EffectNetwork(
    features=(Discrete("visible", (False, True)), Continuous("position", 1)),
    actions=("look", "remove", "tap"),
    parameters=(
        Parameter("force", low=0.0, high=20.0, bins=8, actions=("tap",), affects="position"),
    ),
)


def closed_form(parameters):
    """README's network with the parents its learned structure has: tables and Gaussians."""
    parents = {"end.visible": ("initial.visible", "action"), "end.position": ("action",)}
    return EffectNetwork(README_NET.features, README_NET.actions, parameters, parents=parents)


def readme_rows(n=300, seed=0):
    """README's rows (its third snippet), ``n`` of them."""
    rng = np.random.default_rng(seed)
    action = rng.choice(README_NET.actions, n)
    visible = rng.random(n) < 0.7
    position = rng.uniform(-1.0, 1.0, (n, 1))
    force = np.where(action[:, None] == "tap", rng.uniform(0.0, 20.0, (n, 1)), np.nan)
    rolled = 0.02 * np.nan_to_num(force) + 0.0015 * np.nan_to_num(force) ** 2
    return {
        "initial.visible": visible,
        "initial.position": position,
        "action": action,
        "param.force": force,
        "end.visible": visible & (action != "remove"),
        "end.position": position + rolled + rng.normal(0.0, 0.01, (n, 1)),
    }


def readme_trials(data):
    """README's frame with gaps: labels nobody wrote down, occluded measurements."""
    trials = to_frame(README_NET, data).astype({"end.visible": object})
    trials.loc[::10, "end.visible"] = None
    trials.loc[5::10, "end.position"] = float("nan")
    return trials


def readme_dict(data):
    """The same gaps as a dict: NaN in the continuous value, a mask for the labels."""
    n = len(data["action"])
    seen = np.ones(n, dtype=bool)
    seen[::10] = False
    position = np.array(data["end.position"], dtype=float)
    position[5::10] = np.nan
    return data | {"end.position": position}, {"end.visible": seen}


@pytest.fixture(scope="module")
def readme():
    data = readme_rows()
    rows, masks = readme_dict(data)
    return data, readme_trials(data), rows, masks


def assert_same_params(a, b, tol=1e-12):
    assert set(a.cpds) == set(b.cpds)
    for site, cpd in a.cpds.items():
        for field in dataclasses.fields(cpd):
            x, y = getattr(cpd, field.name), getattr(b.cpds[site], field.name)
            if isinstance(x, torch.Tensor):
                torch.testing.assert_close(x, y, rtol=tol, atol=tol, equal_nan=True)
            else:
                assert x == y, (site, field.name)


# ------------------------------------------------------------ README's frame, every entry point
def test_fit_takes_the_frame_as_the_dict_with_masks(readme):
    _, trials, rows, masks = readme
    assert_same_params(fit(README_NET, trials).params, fit(README_NET, rows, masks=masks).params)


def test_scores_take_the_frame_as_the_dict_with_masks(readme):
    _, trials, rows, masks = readme
    params = fit(README_NET, trials).params
    framed = log_likelihood(README_NET, params, trials)
    given = log_likelihood(README_NET, params, rows, masks=masks)
    torch.testing.assert_close(framed.per_row, given.per_row, rtol=1e-12, atol=1e-12)
    assert bic(README_NET, params, trials) == pytest.approx(
        bic(README_NET, params, rows, masks=masks), rel=1e-12
    )
    assert aic(README_NET, params, trials) == pytest.approx(
        aic(README_NET, params, rows, masks=masks), rel=1e-12
    )


def test_cross_validate_takes_readmes_frame_with_gaps(readme):
    """It raised TypeError ('Partial' object is not iterable): the folds were cut from the
    rows as given, not as read."""
    _, trials, rows, masks = readme
    cv = cross_validate(README_NET, trials, folds=3)
    assert bool(torch.isfinite(cv.per_row).all())
    same = cross_validate(README_NET, rows, folds=3, masks=masks)
    torch.testing.assert_close(cv.per_row, same.per_row, rtol=1e-12, atol=1e-12)
    # each fold: the fit on the others' rows, read as fit reads them, scores it
    read = read_rows(README_NET, trials)
    held, rest = (cv.fold == 0).nonzero().squeeze(-1), (cv.fold != 0).nonzero().squeeze(-1)
    params = fit(README_NET, read.take(rest)).params
    expected = log_likelihood(README_NET, params, read.take(held)).per_row
    torch.testing.assert_close(cv.per_row[held], expected, rtol=1e-12, atol=1e-12)


def test_cross_validate_cuts_partial_values_and_masks_row_wise():
    data = readme_rows(120)
    position = np.array(data["end.position"], dtype=float)
    seen = np.ones((120, 1), dtype=bool)
    seen[3::7] = False
    partial = data | {"end.position": Partial(position, observed=seen)}
    nan = data | {"end.position": np.where(seen, position, np.nan)}
    masks = {"end.visible": np.arange(120) % 9 != 0}
    a = cross_validate(README_NET, partial, folds=2, masks=masks)
    b = cross_validate(README_NET, nan, folds=2, masks=masks)
    torch.testing.assert_close(a.per_row, b.per_row, rtol=1e-12, atol=1e-12)


def test_select_clusters_takes_the_frame_with_gaps(readme):
    _, trials, rows, masks = readme
    for score in ("bic", "heldout"):
        framed = select_clusters(README_NET, trials, [2, 8], score=score, folds=2)
        # a dict with the same gaps, the labels' as None in an object column
        labels = np.array(rows["end.visible"], dtype=object)
        labels[~masks["end.visible"]] = None
        given = select_clusters(
            README_NET, rows | {"end.visible": labels}, [2, 8], score=score, folds=2
        )
        masked = select_clusters(README_NET, rows, [2, 8], score=score, folds=2, masks=masks)
        for other in (given, masked):
            assert framed.chosen.bins == other.chosen.bins
            for x, y in zip(framed.candidates, other.candidates, strict=True):
                assert x.log_likelihood == pytest.approx(y.log_likelihood, rel=1e-12)


def test_learn_structure_refuses_gaps_naming_them_and_the_way_out(readme):
    data, trials, rows, masks = readme
    args = README_NET.features, README_NET.actions, README_NET.parameters
    labels = np.array(rows["end.visible"], dtype=object)
    labels[~masks["end.visible"]] = None
    for form in (trials, rows | {"end.visible": labels}):
        with pytest.raises(ValueError, match=r"\['end.position', 'end.visible'\]") as e:
            learn_structure(form, *args)
        assert "30 of the 300 rows miss 'end.position'" in str(e.value)
        assert "dropna(subset=['end.position', 'end.visible'])" in str(e.value)
        assert "declared structure" in str(e.value)
    # the way out: the complete rows, as a frame, learn what the complete dict does
    learned = learn_structure(trials.dropna(subset=["end.position", "end.visible"]), *args)
    complete = masks["end.visible"] & ~np.isnan(rows["end.position"][:, 0])
    same = learn_structure({k: v[complete] for k, v in data.items()}, *args)
    assert dict(learned.parents) == dict(same.parents)


def test_chunks_read_each_frame_as_one_mapping(readme):
    data, _, _, _ = readme
    net = closed_form(README_NET.parameters)  # chunks serve closed forms
    frame = to_frame(net, data)
    halves = [frame.iloc[:150], frame.iloc[150:]]
    assert_same_params(fit(net, iter(halves)).params, fit(net, data).params, tol=1e-9)


def test_chunks_with_gaps_are_refused_naming_the_sites_and_rows(readme):
    _, trials, _, _ = readme
    with pytest.raises(ValueError, match=r"chunk 0: .*\['end.position', 'end.visible'\]") as e:
        fit(README_NET, iter([trials.iloc[:150], trials.iloc[150:]]))
    assert "15 of the 150 rows miss 'end.position'" in str(e.value)
    assert "one mapping or DataFrame" in str(e.value)


def test_adaptive_em_refuses_gaps_naming_the_sites_and_the_way_out(readme):
    _, trials, _, _ = readme
    p = dataclasses.replace(README_NET.parameters[0], layout="adaptive", bins=3)
    net = closed_form((p,))  # EM over adaptive clusters serves closed forms
    with pytest.raises(ValueError, match=r"30 of the 300 rows miss 'end.visible'.*dropna\(subset="):
        fit_em(net, trials)


# ------------------------------------------------------------ the property: forms agree
@st.composite
def small_networks(draw):
    """One or two features, discrete (labels of bools, ints or strings) or continuous
    (one or two dimensions), sparse parents, perhaps a parameter on a grid."""
    n = draw(st.integers(1, 2))
    labels = [(False, True), (0, 1, 2), ("lo", "hi")]
    features = []
    for i in range(n):
        if draw(st.booleans()):
            features.append(Discrete(f"d{i}", draw(st.sampled_from(labels))))
        else:
            features.append(Continuous(f"c{i}", draw(st.integers(1, 2))))
    parents = {}
    for f in features:
        pool = [f"initial.{g.name}" for g in features] + ["action"]
        parents[f"end.{f.name}"] = tuple(draw(st.lists(st.sampled_from(pool), unique=True)))
    parameters = ()
    continuous = [f for f in features if isinstance(f, Continuous)]
    if continuous and draw(st.booleans()):
        parameters = (Parameter("p", 0.0, 4.0, 2, ("a",), continuous[0].name),)
        site = f"end.{continuous[0].name}"
        parents[site] = tuple(dict.fromkeys((*parents[site], "action")))
    return EffectNetwork(tuple(features), ("a", "b"), parameters, parents=parents)


def three_forms(net, rows, gaps):
    """The rows as a dict (gaps: NaN and masks), as a frame and through CSV (gaps: None
    and NaN in the columns)."""
    rows = {k: v for k, v in rows.items() if not k.startswith("cluster.")}
    frame = to_frame(net, rows)
    n = len(frame)
    masks = {}
    given = dict(rows)
    if gaps:
        for f in net.features:
            site = f"end.{f.name}"
            missing = np.arange(n) % 5 == 2
            if isinstance(f, Discrete):
                frame[site] = frame[site].astype(object)
                frame.loc[missing, site] = None
                masks[site] = ~missing
            else:
                for column in [c for c in frame.columns if c.split("[")[0] == site]:
                    frame.loc[missing, column] = np.nan
                value = torch.as_tensor(rows[site]).clone()
                value[torch.as_tensor(missing)] = torch.nan
                given[site] = value
    text = io.StringIO()
    frame.to_csv(text, index=False)
    text.seek(0)
    return (given, masks), (frame, None), (pd.read_csv(text), None)


FORMS = settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@FORMS
@given(net=small_networks(), seed=st.integers(0, 2**16), gaps=st.booleans())
def test_every_entry_point_reads_every_form_alike(net, seed, gaps):
    rows = simulate(net, random_params(net, seed), 60, seed=seed)
    forms = three_forms(net, rows, gaps)
    fits = [fit(net, data, masks=masks, steps=4).params for data, masks in forms]
    for other in fits[1:]:
        assert_same_params(fits[0], other)
    scored = [log_likelihood(net, fits[0], d, masks=m).per_row for d, m in forms]
    cvs = [cross_validate(net, d, folds=2, seed=seed, masks=m, steps=4).per_row for d, m in forms]
    for results in (scored, cvs):
        for other in results[1:]:
            torch.testing.assert_close(results[0], other, rtol=1e-12, atol=1e-12)
    if not gaps:
        halves = [
            [{k: v[:30] for k, v in d.items()}, {k: v[30:] for k, v in d.items()}]
            if isinstance(d, dict)
            else [d.iloc[:30], d.iloc[30:]]
            for d, _ in forms
        ]
        if not any(net.cpd(s.name).name == "softmax" for s in net.sites):
            for chunks in halves:
                assert_same_params(fits[0], fit(net, iter(chunks)).params, tol=1e-9)
        learned = [learn_structure(d, net.features, net.actions, net.parameters) for d, _ in forms]
        assert all(dict(x.parents) == dict(learned[0].parents) for x in learned)
