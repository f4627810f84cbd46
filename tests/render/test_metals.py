"""Mitsuba 3's named conductors (hlbvh_cl/render/metals.py, read by
materials.py) against the installed Mitsuba 3 itself: every name it ships
spectral data for is in the table, and each name's eta and k, as our
material records carry them, are the RGB values Mitsuba's scalar_rgb
variant gives the same conductor; so the table cannot drift from Mitsuba
unseen.  The renders of named metals beside Mitsuba's are in test_path.py."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hlbvh_cl.render.materials import check_material
from hlbvh_cl.render.metals import METALS

mi = pytest.importorskip("mitsuba")


def mitsuba_index(name: str) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's (eta, k) of its conductor named ``name``, float32 RGB."""
    mi.set_variant("scalar_rgb")
    parameters = mi.traverse(mi.load_dict({"type": "conductor", "material": name}))
    return tuple(np.array(parameters[f"{key}.value"], np.float32).ravel() for key in ("eta", "k"))


def test_each_named_metal_has_mitsuba_s_rgb_eta_and_k():
    wrong = []
    for name in METALS:
        theirs = mitsuba_index(name)
        for kind in ("conductor", "roughconductor"):
            record = check_material(f"{kind} {name}", {"type": kind, "material": name})
            ours = (record["eta"], record["k"])
            if not all(np.allclose(a, b, rtol=1e-6, atol=1e-9) for a, b in zip(ours, theirs)):
                wrong.append(f"{kind} {name}: ours eta {ours[0]}, k {ours[1]}; Mitsuba "
                             f"{mi.__version__}'s eta {theirs[0]}, k {theirs[1]}")
    assert not wrong, "\n".join(wrong)


def test_every_metal_mitsuba_ships_is_named():
    folder = Path(mi.__file__).parent / "data" / "ior"
    if not folder.is_dir():
        pytest.skip(f"this Mitsuba keeps no data/ior folder beside {mi.__file__}")
    shipped = {path.name.split(".")[0] for path in folder.glob("*.eta.spd")}
    assert shipped and shipped == set(METALS), (sorted(shipped - set(METALS)),
                                                sorted(set(METALS) - shipped))


def test_none_is_the_mirror_and_takes_eta_and_k_as_in_mitsuba():
    """"none" (Mitsuba's default) is eta 0 and k 1, and, unlike a name,
    allows eta and k beside it, as Mitsuba does."""
    mi.set_variant("scalar_rgb")
    for spec in ({"type": "conductor"}, {"type": "conductor", "material": "none", "eta": 2.0}):
        theirs = mi.traverse(mi.load_dict(spec))
        record = check_material("m", spec)
        for key in ("eta", "k"):  # Mitsuba keeps a number as a grey value
            assert record[key] == pytest.approx(np.broadcast_to(theirs[f"{key}.value"], 3))


@pytest.mark.parametrize("extra", [{"eta": 1.0}, {"k": 1.0}])
def test_mitsuba_too_refuses_a_name_beside_eta_or_k(extra):
    """The oracle of materials.py's error for a name with eta or k (its
    message is checked in test_path.py): Mitsuba refuses both."""
    mi.set_variant("scalar_rgb")
    with pytest.raises(RuntimeError):
        mi.load_dict({"type": "conductor", "material": "Au", **extra})
    with pytest.raises(ValueError, match="give either the material 'Au' or eta and k"):
        check_material("m", {"type": "conductor", "material": "Au", **extra})
