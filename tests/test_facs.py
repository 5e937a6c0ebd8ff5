"""FACS tables: AU -> controls, emotion presets, and the inverse readout (NNLS)."""

import numpy as np
import pytest

from jaxface import facs
from jaxface.anatomy.muscle_map import load_muscle_map
from jaxface.errors import RigError


@pytest.fixture(scope="module")
def names():
    return tuple(s.name for s in load_muscle_map() if s.active)


def test_every_table_muscle_exists_in_the_default_map(names):
    bases = {n[:-2] if n.endswith(("_L", "_R")) else n for n in names}
    for au, row in facs.AU_MUSCLES.items():
        for m in row:
            assert m in bases, f"{au} refers to {m}, which the default map does not have"


def test_parse_aus():
    assert facs.parse_aus("AU12=0.8,AU26") == {"AU12": 0.8, "AU26": 1.0}
    assert facs.parse_aus(["au12l=0.5"]) == {"AU12L": 0.5}
    for bad in ("AU12=2", "AUx", "AU99=0.5", "AU12=abc"):
        with pytest.raises(RigError):
            facs.parse_aus(bad)


def test_bilateral_and_unilateral_expansion(names):
    both = facs.expand_au("AU12", names)
    assert both == {"zygomaticus_major_L": 1.0, "zygomaticus_major_R": 1.0}
    assert facs.expand_au("AU12L", names) == {"zygomaticus_major_L": 1.0}
    assert facs.expand_au("AU12R", names) == {"zygomaticus_major_R": 1.0}
    # a mid-line muscle gets half of its weight in a one-sided AU
    assert facs.expand_au("AU4L", names)["procerus"] == pytest.approx(0.3)


def test_controls_of_aus_and_jaw(names):
    a, jaw, puff = facs.aus_to_controls({"AU12": 0.5, "AU26": 1.0, "AU34": 0.4}, names)
    i = names.index("zygomaticus_major_L")
    assert a[i] == pytest.approx(0.5) and a.sum() == pytest.approx(1.0)
    assert float(jaw.pitch_deg) == pytest.approx(10.0) and puff == pytest.approx(0.4)
    a, jaw, _ = facs.aus_to_controls({"AU30R": 1.0, "AU29": 0.5}, names)
    assert float(jaw.yaw_deg) < 0 and float(jaw.protrusion_mm) == pytest.approx(2.5)
    assert not a.any()


def test_the_cheek_puff_by_side_and_as_the_fits_controls(names):
    """AU34L / AU34R puff one cheek (``[left, right]``), a bilateral AU34 both (a number);
    where the control names include the fit's two cheek pressures the puff is in the
    activations, the AU table has an AU34 row per side, and the readout reads it back."""
    from jaxface.anatomy.cheek_puff import PUFF_CONTROLS

    _, _, puff = facs.aus_to_controls({"AU34L": 0.7}, names)
    np.testing.assert_array_equal(puff, [0.7, 0.0])
    _, _, puff = facs.aus_to_controls({"AU34L": 0.7, "AU34R": 0.7}, names)
    assert puff == pytest.approx(0.7) and np.ndim(puff) == 0
    _, _, puff = facs.aus_to_controls({"AU34": 0.5, "AU34R": 0.8}, names)  # clipped at 1
    np.testing.assert_allclose(puff, [0.5, 1.0])
    read = facs.au_intensities(np.zeros(len(names)), names, cheek_puff=np.array([0.6, 0.2]))
    assert (read["AU34L"], read["AU34R"], read["AU34"]) == pytest.approx((0.6, 0.2, 0.4))
    assert "AU34L" not in facs.au_intensities(np.zeros(len(names)), names, cheek_puff=0.3)
    # the fit's controls: the muscles, then the two cheek pressures
    fit_names = (*names, *PUFF_CONTROLS)
    assert facs.expand_au("AU34", fit_names) == {"cheek_puff_L": 1.0, "cheek_puff_R": 1.0}
    assert facs.expand_au("AU34R", fit_names) == {"cheek_puff_R": 1.0}
    assert facs.expand_au("AU34", names) == {}
    a, _, puff = facs.aus_to_controls({"AU34L": 0.7, "AU12": 0.5}, fit_names)
    assert puff == 0.0 and list(a[-2:]) == [0.7, 0.0]
    aus, A = facs.au_matrix(fit_names)
    assert aus[-2:] == ["AU34L", "AU34R"] and A[-2:, -2:].tolist() == [[1, 0], [0, 1]]
    assert "AU34L" not in facs.au_matrix(names)[0]
    read = facs.au_intensities(a, fit_names)
    assert read["AU34L"] == pytest.approx(0.7) and read["AU34R"] == pytest.approx(0.0)
    assert read["AU12"] == pytest.approx(0.5)


@pytest.mark.parametrize(
    "emotion,aus",
    [
        ("happiness", {"AU6", "AU12"}),
        ("sadness", {"AU1", "AU4", "AU15"}),
        ("surprise", {"AU1", "AU2", "AU5", "AU26"}),
        ("fear", {"AU1", "AU2", "AU4", "AU5", "AU20", "AU26"}),
        ("anger", {"AU4", "AU5", "AU7", "AU23"}),
        ("disgust", {"AU9", "AU15", "AU16"}),
    ],
)
def test_emotion_presets(emotion, aus, names):
    assert set(facs.EMOTIONS[emotion]) == aus
    a, jaw, _ = facs.emotion_controls(emotion, names)
    assert a.max() <= 1.0 and a.min() >= 0.0 and a.any()
    assert (float(jaw.pitch_deg) > 0) == ("AU26" in aus)


def test_readout_inverts_the_table(names):
    rng = np.random.default_rng(3)
    aus, A = facs.au_matrix(names)
    # a random sparse set of distinguishable AUs
    pick = {
        "AU1L": 0.7,
        "AU1R": 0.6,
        "AU12L": 0.9,
        "AU15R": 0.4,
        "AU9L": 0.5,
        "AU9R": 0.5,
        "AU17L": 0.3,
        "AU17R": 0.3,
        "AU20L": 0.8,
    }
    a = np.zeros(len(names))
    for au, v in pick.items():
        a += v * A[aus.index(au)]
    a = np.clip(a + rng.normal(0, 1e-4, a.shape), 0, 1)
    out = facs.au_intensities(a, names)
    for au, v in pick.items():
        assert out[au] == pytest.approx(v, abs=2e-3), au
    assert out["AU12"] == pytest.approx(0.45, abs=2e-3)  # mean of the sides
    assert out["AU12L"] > out["AU12R"] + 0.8  # side is recovered
    strongest = sorted((k for k in out if not k.endswith(("L", "R"))), key=lambda k: -out[k])[:3]
    assert "AU20" not in strongest or out["AU20"] == pytest.approx(0.4, abs=5e-3)


def test_readout_of_jaw_and_emotions(names):
    from jaxface.anatomy.jaw import JawPose

    # the jaw readout inverts the table's jaw: AU26 / AU27 at any intensity, and their pitch
    for aus in ({"AU26": 0.3}, {"AU26": 1.0}, {"AU27": 1.0}, {"AU26": 0.25, "AU27": 0.75}):
        _, jaw, _ = facs.aus_to_controls(aus, names)
        out = facs.au_intensities(np.zeros(len(names)), names, jaw)
        for au in ("AU26", "AU27"):
            assert out[au] == pytest.approx(aus.get(au, 0.0), abs=1e-12), (aus, out)

    out = facs.au_intensities(np.zeros(len(names)), names, JawPose(14.0, -4.0, 2.5))
    # 14 degrees: half way from AU26's 10 to AU27's 18, read as half of each
    assert out["AU26"] == pytest.approx(0.5) and out["AU27"] == pytest.approx(0.5)
    assert out["AU29"] == pytest.approx(0.5) and out["AU30R"] == pytest.approx(1.0)
    a, jaw, _ = facs.emotion_controls("surprise", names)
    out = facs.au_intensities(a, names, jaw)
    top = sorted((k for k in out if not k.endswith(("L", "R"))), key=lambda k: -out[k])[:4]
    assert set(top) == {"AU1", "AU2", "AU5", "AU26"}


def test_bad_inputs(names):
    with pytest.raises(RigError, match="entries"):
        facs.au_intensities(np.zeros(3), names)
    with pytest.raises(RigError, match="unknown emotion"):
        facs.emotion_controls("boredom", names)


def test_intensity_letters_follow_the_facs_bins():
    from jaxface.facs import INTENSITY_LETTERS, intensity_letter, intensity_letters

    bounds = [lo for _, lo in INTENSITY_LETTERS]
    assert bounds == sorted(bounds) and bounds[0] > 0 and bounds[-1] < 1
    assert intensity_letter(0.0) is None and intensity_letter(0.099) is None
    expected = {0.1: "A", 0.2: "A", 0.3: "B", 0.5: "C", 0.69: "C", 0.7: "D", 0.95: "E", 1.0: "E"}
    for x, letter in expected.items():
        assert intensity_letter(x) == letter, x
    # every letter is reachable, in order, as the intensity grows
    seen = [intensity_letter(x) for x in np.linspace(0, 1, 1001)]
    assert [k for i, k in enumerate(seen) if k and (i == 0 or seen[i - 1] != k)] == list("ABCDE")
    assert intensity_letters({"AU12": 0.8, "AU6": 0.05, "AU1": 0.3}) == {"AU12": "D", "AU1": "B"}
    with pytest.raises(ValueError, match="finite"):
        intensity_letter(float("nan"))


def test_sided_aus_code_even_aus_once_and_uneven_ones_per_side():
    vals = {
        "AU12": 0.3,  # one-sided smile: L 0.6, R 0
        "AU12L": 0.6,
        "AU12R": 0.0,
        "AU1": 0.7,  # even brow raise
        "AU1L": 0.72,
        "AU1R": 0.68,
        "AU4": 0.2,  # uneven frown: both sides listed
        "AU4L": 0.35,
        "AU4R": 0.05,
        "AU26": 0.5,  # the jaw: no sides
        "AU15": 0.002,  # below the floor
        "AU15L": 0.002,
        "AU15R": 0.002,
    }
    got = facs.sided_aus(vals)
    assert got == [("AU1", 0.7), ("AU12L", 0.6), ("AU26", 0.5), ("AU4L", 0.35), ("AU4R", 0.05)]
    assert facs.sided_aus(vals, 2) == got[:2]
    # the tolerance decides: at 0.3 the frown is even and listed once, bilaterally
    assert ("AU4", 0.2) in facs.sided_aus(vals, asymmetry=0.3)
    assert ("AU15", 0.002) in facs.sided_aus(vals, floor=0.0)
    assert facs.sided_aus({"AU9L": 0.4}) == [("AU9L", 0.4)]  # a side without its bilateral key
    with pytest.raises(ValueError, match="finite"):
        facs.sided_aus({"AU1": float("nan")})
    with pytest.raises(ValueError, match=">= 0"):
        facs.sided_aus(vals, asymmetry=-0.1)
