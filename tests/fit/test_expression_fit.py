"""The fit result's JSON frame report (:meth:`jaxface.fit.expression_fit.ExpressionFit.frame_dict`):
the face's directions measured from the scan's landmarks, and the convention claimed only
when they follow it."""

from types import SimpleNamespace

import numpy as np

from jaxface.fit.expression_fit import ExpressionFit
from jaxface.landmarks import Landmarks
from jaxface.rigid import rotation_from_euler


def _frame(landmarks):
    return ExpressionFit.frame_dict(
        SimpleNamespace(scan=SimpleNamespace(landmarks=landmarks), stem="s")
    )  # type: ignore[arg-type]


def _head_landmarks():
    from jaxface.head import generic_head

    return generic_head().landmarks


def test_upright_scan_claims_the_convention():
    d = _frame(_head_landmarks())
    assert d["conventional"] is True and d["units"] == "mm"
    assert d["axes"].startswith("+y up, +z toward the viewer")
    assert max(d["angles_to_convention_deg"].values()) < 5.0
    np.testing.assert_allclose(d["face_axes"]["up"], [0, 1, 0], atol=0.08)


def test_turned_scan_says_which_way_the_face_looks():
    """The same face turned 90 degrees about x (looking up, +y) and 180 about y: the report
    gives the turned directions and does not claim +y up."""
    lm = _head_landmarks()
    for pitch, yaw, forward in ((-90.0, 0.0, [0, 1, 0]), (0.0, 180.0, [0, 0, -1])):
        R = rotation_from_euler(pitch, yaw)
        turned = Landmarks(lm.names, np.asarray(lm.positions) @ R.T)
        d = _frame(turned)
        assert d["conventional"] is False, d
        assert d["axes"].startswith("not the convention")
        np.testing.assert_allclose(d["face_axes"]["forward"], forward, atol=0.2)
        np.testing.assert_allclose(
            np.array([d["face_axes"][k] for k in ("left", "up", "forward")]),
            np.array([_frame(lm)["face_axes"][k] for k in ("left", "up", "forward")]) @ R.T,
            atol=1e-3,
        )


def test_frame_without_the_needed_landmarks_is_not_measured():
    lm = _head_landmarks()
    keep = [i for i, n in enumerate(lm.names) if "mouth corner" not in n]
    d = _frame(Landmarks([lm.names[i] for i in keep], np.asarray(lm.positions)[keep]))
    assert d["conventional"] is None and d["face_axes"] is None
    assert "not measured" in d["axes"] and "mouth corner" in d["axes"]
