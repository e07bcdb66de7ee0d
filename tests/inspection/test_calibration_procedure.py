"""inspection.calibrating / calibration: the calibration procedure as functions, the estimator's defaults, the one
kept-points and noise-floor rules, and versioned calibration records (a version-1 record loads and scores as it was
calibrated; a fresh one round-trips)."""
import inspect
from dataclasses import fields

import numpy as np
import pytest

from inspection import Inspector
from inspection.calibration import CALIBRATION_VERSION, EXTRA_KEYS, Calibration, migrate
from inspection.config import InspectionConfig
from inspection.reference import LocalReference
from inspection.threshold import fit_threshold
from tests.inspection.spheres import ScaledSphereModel, SphereField, SphereModel, sphere_scan


def sphere_points(n=600, seed=0, dent=0.0):
    """(m, 3) points of one view of the half sphere (:func:`tests.inspection.spheres.sphere_scan`)."""
    return sphere_scan(n=n, seed=seed, dent=dent)[0]


@pytest.fixture(scope="module")
def joint():
    """A 'joint' inspector of the sphere model: 4 held-back scans, 6 reference scans cross-fitted; and new scans."""
    good = [sphere_points(seed=s) for s in range(6)]
    held = [sphere_points(seed=s) for s in range(20, 24)]
    new = [sphere_points(seed=40), sphere_points(seed=41, dent=0.05)]
    insp = Inspector(SphereModel(), point_score="joint", alpha=0.2).fit(held, reference_scans=good)
    return insp, held, good, new


def test_inspector_defaults_are_the_inspection_config_fields():
    """Inspector's parameters are InspectionConfig's fields, in order, with the same defaults (then ``verbose``)."""
    params = list(inspect.signature(Inspector.__init__).parameters.values())
    assert [p.name for p in params[:2]] == ["self", "model"] and params[-1].name == "verbose"
    assert [(p.name, p.default) for p in params[2:-1]] == [(f.name, f.default) for f in fields(InspectionConfig)]
    assert Inspector(SphereModel()).config == InspectionConfig()


def test_calibrate_returns_the_fitted_state_that_fit_adopts(joint):
    from inspection.calibrating import calibrate

    insp, held, good, _ = joint
    fit = calibrate(SphereModel(), held, InspectionConfig(point_score="joint", alpha=0.2), reference_scans=good)
    assert fit.parts is None and fit.reading is None and fit.fingerprint == ""
    state = fit.state
    np.testing.assert_array_equal(state.scores, insp.calibration_scores_)
    assert state.names == insp.calibration_names_ and state.roles == insp.calibration_roles_
    assert state.roles == ["held-back"] * 4 + ["cross-fitted"] * 6
    assert state.settings == insp.settings_ and state.settings.align is False and state.source == \
        insp.calibration_source_
    assert state.reference.term_variances == insp.reference_.term_variances != (1.0, 1.0)
    assert state.combination is None and state.aligner is None
    # the threshold is the estimator's, at its alpha
    assert insp.threshold_ == fit_threshold(state.scores, 0.2, state.roles).value


def test_kept_points_leaves_the_stray_returns_out_unless_every_point_is_stray():
    from inspection.evidence import kept_points

    np.testing.assert_array_equal(kept_points(None, 3), [True, True, True])
    np.testing.assert_array_equal(kept_points(np.array([False, True, False]), 3), [True, False, True])
    np.testing.assert_array_equal(kept_points(np.array([True, True]), 2), [True, True])
    with pytest.raises(ValueError, match="3 points but 2 stray flags"):
        kept_points(np.array([True, False]), 3)


def test_noise_floor_is_the_settings_else_the_fields_own():
    from inspection.scores import noise_floor

    field = SphereField(noise=0.01)
    assert noise_floor(field) == 0.01 and noise_floor(field, 0.0) == 0.0 and noise_floor(field, 0.2) == 0.2
    assert noise_floor(object()) == 0.0  # a field without a noise of its own


def test_a_fresh_record_round_trips_at_the_current_version(joint):
    insp, held, _, new = joint
    record = insp.calibration(source="unit test").as_dict()
    assert record["version"] == CALIBRATION_VERSION and set(EXTRA_KEYS) <= set(record["extra"])
    again = migrate(record)
    assert again is not record and again["extra"].keys() == record["extra"].keys()
    assert again["roles"] == record["roles"] and again["extra"]["config"] == record["extra"]["config"]
    restored = Inspector.from_calibration(SphereModel(), Calibration.from_dict(record))
    assert restored.settings_ == insp.settings_ and restored.threshold_ == insp.threshold_
    assert restored.calibration_roles_ == insp.calibration_roles_ and not restored.level_rendered_
    np.testing.assert_array_equal(restored.anomaly_scores(held + new), insp.anomaly_scores(held + new))
    np.testing.assert_array_equal(restored.anomaly_map(new[1]), insp.anomaly_map(new[1]))


def _version_1(record):
    """``record`` as the first calibrations stored it: version 1, no roles, no settings stored whole (the projection
    under ``extra``), no level_rendered / reading / align, and a reference of points and values alone."""
    reference = record["extra"]["reference"]
    return {"version": 1, "scores": record["scores"], "names": record["names"], "aggregate": record["aggregate"],
            "point_score": record["point_score"], "noise": record["noise"], "alpha": record["alpha"],
            "source": record["source"], "fingerprint": "",
            "extra": {"projection": None, "reference": {"points": reference["points"],
                                                        "values": reference["values"]}}}


def test_a_version_1_record_loads_and_scores_as_it_was_calibrated(joint):
    """A version-1 record with its older keys missing is upgraded as read: what the code of its time did without
    them (no registration, every calibration scan held back, the reference alone with equal term weights and the
    good points' term kept on unseen faces); it scores exactly as an inspector holding that state."""
    insp, held, _, new = joint
    old = _version_1(insp.calibration().as_dict())
    kept = {k: (dict(v) if isinstance(v, dict) else v) for k, v in old.items()}
    upgraded = migrate(old)
    assert old == kept  # the record given is not modified
    assert upgraded["version"] == CALIBRATION_VERSION and set(EXTRA_KEYS) <= set(upgraded["extra"])
    assert upgraded["roles"] == ["held-back"] * len(old["scores"]) and "projection" not in upgraded["extra"]
    restored = Inspector.from_calibration(SphereModel(), Calibration.from_dict(old))
    settings = restored.settings_
    assert (settings.point_score, settings.aggregate, settings.projection, settings.rays, settings.align) == \
           ("joint", insp.settings_.aggregate, None, False, False)
    assert restored.aligner_ is None and restored.combination_ is None and not restored.level_rendered_
    assert restored.threshold_ == fit_threshold(old["scores"], old["alpha"]).value
    reference = restored.reference_
    assert (reference.variance_scale, reference.grazing_scale, reference.term_variances) == (0.0, 0.0, (1.0, 1.0))
    assert not reference.field_on_unseen_faces and reference.surface_points is None
    # the same state by hand: the stored reference points and values alone, scored by today's inspector
    by_hand = Inspector.from_calibration(SphereModel(), insp.calibration())
    by_hand.settings_ = settings
    by_hand.reference_ = LocalReference(reference.points, reference.values, field_on_unseen_faces=False)
    np.testing.assert_array_equal(restored.anomaly_scores(held + new), by_hand.anomaly_scores(held + new))


def test_a_version_1_record_stored_whole_keeps_its_settings_and_parts_are_upgraded_too(joint):
    insp = joint[0]
    record = insp.calibration().as_dict()
    config = {k: v for k, v in record["extra"]["config"].items() if k != "align"}  # before registration existed
    older = {**record, "version": 1, "roles": [],
             "extra": {"config": config, "reference": record["extra"]["reference"]}}
    upgraded = migrate(older)
    # before registration existed: never registered; before coverage: every point counted
    assert upgraded["extra"]["config"] == {**record["extra"]["config"], "align": False, "coverage": 0.0}
    assert upgraded["extra"]["reference"] == record["extra"]["reference"]  # complete already: kept as it is
    several = {**older, "extra": {**older["extra"], "reference": None, "parts": {"a": older, "b": older}}}
    parts = migrate(several)["extra"]["parts"]
    assert all(p["version"] == CALIBRATION_VERSION and p["roles"] == upgraded["roles"] for p in parts.values())


def test_a_version_2_record_counts_every_point_as_it_was_calibrated(joint):
    """A version-2 record (before coverage) upgrades to coverage 0: its scans are scored over every point, as its
    calibration scores were; a fresh record stores the coverage it scored with."""
    _, held, good, new = joint
    insp = Inspector(ScaledSphereModel(), point_score="joint", alpha=0.2, coverage=0.5).fit(held,
                                                                                             reference_scans=good)
    assert all(insp.inspect(s).coverage is not None for s in new)  # a field with a lengthscale: coverage applies
    record = insp.calibration().as_dict()
    assert record["extra"]["config"]["coverage"] == 0.5  # the setting in force is stored
    older = {**record, "version": 2,
             "extra": {**record["extra"], "config": {k: v for k, v in record["extra"]["config"].items()
                                                     if k != "coverage"}}}
    upgraded = migrate(older)
    assert upgraded["version"] == CALIBRATION_VERSION and upgraded["extra"]["config"]["coverage"] == 0.0
    restored = Inspector.from_calibration(ScaledSphereModel(), Calibration.from_dict(older))
    assert restored.settings_.coverage == 0.0
    assert all(restored.inspect(s).coverage is None for s in new)


def test_a_record_of_an_unknown_version_is_one_clear_error():
    for version in (0, CALIBRATION_VERSION + 1, "2", None):
        with pytest.raises(ValueError, match=f"model.pt: calibration record of unsupported version {version!r}"):
            Calibration.from_dict({"version": version, "scores": [1.0]}, source="model.pt")


def test_a_damaged_record_is_one_clear_error_naming_the_file(joint):
    """A current record missing an entry, or an older one missing a field its upgrade reads, is a ValueError that
    names the file and what is missing, not a KeyError."""
    record = joint[0].calibration().as_dict()
    del record["extra"]["reference"]
    with pytest.raises(ValueError, match=r"model\.pt: damaged calibration record: no extra\['reference'\]"):
        Calibration.from_dict(record, source="model.pt")
    old = {k: v for k, v in joint[0].calibration().as_dict().items() if k != "aggregate"}
    old["version"], old["extra"] = 1, {}
    with pytest.raises(ValueError, match=r"model\.pt: damaged calibration record of version 1"):
        Calibration.from_dict(old, source="model.pt")
