"""Added tube filtration as the physics settings spell it: element symbols and ``SYMBOL:MM`` items.

The ``filters`` setting (:mod:`sim.physics.settings`) checks its items with :func:`parse_filters`,
and the tube spectrum (:mod:`sim.physics.spectrum`) applies them. Plain Python: no numpy, no
xraylib (a machine that only reads cached spectra lacks it).
"""

from __future__ import annotations

import math
import numbers

from sim.physics import PhysicsError

__all__ = ["ELEMENT_SYMBOLS", "parse_filters"]


#: The chemical elements' symbols in order of atomic number (Z = index + 1): filter symbols are
#: checked against it, without xraylib (a machine that only reads cached spectra lacks it).
ELEMENT_SYMBOLS = tuple((
    "H He Li Be B C N O F Ne Na Mg Al Si P S Cl Ar K Ca Sc Ti V Cr Mn Fe Co Ni Cu Zn Ga Ge As Se Br Kr "
    "Rb Sr Y Zr Nb Mo Tc Ru Rh Pd Ag Cd In Sn Sb Te I Xe Cs Ba La Ce Pr Nd Pm Sm Eu Gd Tb Dy Ho Er Tm Yb "
    "Lu Hf Ta W Re Os Ir Pt Au Hg Tl Pb Bi Po At Rn Fr Ra Ac Th Pa U Np Pu Am Cm Bk Cf Es Fm Md No Lr Rf "
    "Db Sg Bh Hs Mt Ds Rg Cn Nh Fl Mc Lv Ts Og").split())


def parse_filters(items) -> tuple[tuple[str, float], ...]:
    """``["Al:2.5", "Cu:0.1"]`` -> ``(("Al", 2.5), ("Cu", 0.1))`` (element symbol, mm); items that
    are already ``(symbol, mm)`` pairs are checked the same way."""
    out = []
    for item in items:
        if isinstance(item, (tuple, list)) and len(item) == 2:
            sym, sep = str(item[0]), ":"
            mm = item[1] if isinstance(item[1], numbers.Real) and not isinstance(item[1], bool) else "?"
        else:
            sym, sep, mm = str(item).partition(":")
        z = ELEMENT_SYMBOLS.index(sym.strip()) + 1 if sym.strip() in ELEMENT_SYMBOLS else 0
        try:
            t = float(mm)
        except ValueError:
            t = float("nan")
        if not sep or z <= 0 or not (math.isfinite(t) and t >= 0):
            raise PhysicsError(f"filter {item!r}: expected SYMBOL:MM with an element symbol and a thickness "
                               "in mm >= 0, e.g. Al:2.5 or Cu:0.1")
        out.append((sym.strip(), t))
    return tuple(out)
