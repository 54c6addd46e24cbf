"""The simulated lathe's cut program: one ``Cut`` per pass, and its text form.

Apart from lathed.sim.lathe (whose physics imports scipy) so the daemon can
check a [simulator] program in its config without importing the simulator.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

MAX_DEPTH_MM = 10.0   # deepest pass the simulated lathe takes (program, override, config)
MAX_DWELL_S = 60.0    # longest dwell (G04) in a pass: a feed held longer is a stopped program
MAX_OUTAGE_S = 3600.0  # longest peer outage `lathectl sim outage` takes: an hour down is not a test of a retry


@dataclass(frozen=True)
class Cut:
    """One part of the program: a turning pass along the bar at ``rpm`` (G97), or, with
    ``css_m_min``, a facing pass at constant surface speed (G96): the tool moves in from
    the bar's diameter by ``length_mm`` (radially), the speed follows the diameter
    (1000 V / (pi D)) and ``rpm`` is the speed clamp (G50 S).  ``dwell_s``: halfway along
    the pass the feed stops for that long (G04), the tool in the work, then goes on.
    ``thread``: a threading pass (G76/G92), its feed the pitch: the control's threading
    signal is on for its cycle. Only the signal is the control's: the chip is cut as a
    turning pass's (no flank-only chip, no regeneration between a thread's passes)."""
    rpm: float
    depth_mm: float
    feed_mm_rev: float = 0.3
    length_mm: float = 40.0
    diameter_mm: float = 30.0
    css_m_min: float = 0.0
    tool: int = 1                 # the turret position cutting (lathed.sim.lathe.tool_modes)
    # a dwell (G04) at the pass's middle: the feed stops this long with the tool in the work
    # and the spindle turning (a groove's bottom, a shoulder), then the pass goes on
    dwell_s: float = 0.0
    thread: bool = False
    # part-program features along the pass (issue 38), at a travel (mm) into it: a shoulder
    # (the depth becomes step_depth_mm from step_at_mm on: deeper, a larger diameter met; or
    # shallower); a flat or a keyway (flat_deg of every revolution without material from
    # flat_at_mm on: an interrupted cut); a groove cut before (no material over groove_width_mm
    # from groove_at_mm: the tool leaves the work and re-enters)
    step_depth_mm: float | None = None
    step_at_mm: float = 0.0
    flat_deg: float = 0.0
    flat_at_mm: float = 0.0
    groove_at_mm: float = 0.0
    groove_width_mm: float = 0.0

    def depth_at(self, travel_mm: float) -> float:
        """The depth the tool cuts at ``travel_mm`` into the pass (0 over a groove)."""
        if self.groove_width_mm and self.groove_at_mm <= travel_mm < self.groove_at_mm + self.groove_width_mm:
            return 0.0
        if self.step_depth_mm is not None and travel_mm >= self.step_at_mm:
            return self.step_depth_mm
        return self.depth_mm

    def flat_at(self, travel_mm: float) -> float:
        """Degrees of every revolution without material at ``travel_mm`` into the pass."""
        return self.flat_deg if self.flat_deg and travel_mm >= self.flat_at_mm else 0.0

    def program_rpm(self, travel_mm: float) -> float:
        """The speed the program asks for with the tool ``travel_mm`` into the pass."""
        if not self.css_m_min:
            return self.rpm
        return min(self.rpm, 1000.0 * self.css_m_min / (math.pi * max(self.diameter_at(travel_mm), 1e-3)))

    def diameter_at(self, travel_mm: float) -> float:
        """The diameter the tool cuts at ``travel_mm`` into the pass."""
        if not self.css_m_min:
            return self.diameter_mm
        return self.diameter_mm - 2.0 * min(travel_mm, self.length_mm)


FORM = ("RPM,DEPTH_MM[,FEED_MM_REV[,LENGTH_MM]][,css=M_MIN][,tool=N][,dwell=S][,thread=PITCH_MM]"
        "[,step=DEPTH_MM@MM][,flat=DEG[@MM]][,groove=MM+WIDTH_MM]")
TOOLS = (1, 2)        # the simulated turret's positions (their dynamics: lathed.sim.lathe.tool_modes)


def parse_cut(text: str) -> Cut:
    """``RPM,DEPTH_MM[,FEED_MM_REV[,LENGTH_MM]][,css=M_MIN][,tool=N][,dwell=S][,thread=PITCH_MM]``:
    one part of a cut program; with ``css=`` a facing pass at that surface speed (G96), RPM its
    clamp; ``tool=`` the turret position that cuts it (1, the default, or 2); ``dwell=`` seconds
    the feed stops halfway along the pass (G04), the tool in the work; ``thread=`` a threading
    pass of that pitch (its feed); ``step=DEPTH_MM@MM`` a shoulder: the depth becomes DEPTH_MM from
    MM into the pass; ``flat=DEG[@MM]`` a flat or a keyway: DEG of every revolution without
    material (from MM into the pass, else from its start); ``groove=MM+WIDTH_MM`` a groove cut
    before: no material over WIDTH_MM from MM into the pass."""
    items = [x.strip() for x in text.split(",")]
    css, tool, dwell, pitch = 0.0, 1, 0.0, None
    feats: dict = {}
    seen = set()
    while items and "=" in items[-1]:
        key, _, value = items.pop().partition("=")
        if key in seen:
            raise ValueError(f"cut {text!r}: {key}= given twice")
        seen.add(key)
        if key == "css":
            try:
                css = float(value)
            except ValueError:
                raise ValueError(f"cut {text!r}: css= takes a surface speed in m/min") from None
        elif key == "tool":
            if value not in [str(t) for t in TOOLS]:
                raise ValueError(f"cut {text!r}: tool= is a turret position of the simulated lathe: "
                                 f"{', '.join(map(str, TOOLS))}")
            tool = int(value)
        elif key == "dwell":
            try:
                dwell = float(value)
            except ValueError:
                raise ValueError(f"cut {text!r}: dwell= takes seconds") from None
            if not 0 < dwell <= MAX_DWELL_S:
                raise ValueError(f"cut {text!r}: dwell= takes 0..{MAX_DWELL_S:g} s")
        elif key == "thread":
            try:
                pitch = float(value)
            except ValueError:
                raise ValueError(f"cut {text!r}: thread= takes the pitch in mm") from None
            if not 0 < pitch <= 2:
                raise ValueError(f"cut {text!r}: thread= takes a pitch of 0..2 mm")
        elif key in ("step", "flat", "groove"):
            feats.update(_feature(text, key, value))
        else:
            raise ValueError(f"cut {text!r}: unknown {key}=; allowed: css=, tool=, dwell=, thread=, "
                             "step=, flat=, groove=")
    try:
        vals = [float(x) for x in items]
    except ValueError:
        raise ValueError(f"cut {text!r}: expected {FORM} as numbers") from None
    if not 2 <= len(vals) <= 4:
        raise ValueError(f"cut {text!r}: expected {FORM}")
    if pitch is not None:
        if len(vals) >= 3 and vals[2] != pitch:
            raise ValueError(f"cut {text!r}: a thread's feed is its pitch: {vals[2]!r} against thread={pitch!r}")
        if css or dwell or feats:
            raise ValueError(f"cut {text!r}: a threading pass takes no css= (G96), dwell=, step=, flat= or "
                             "groove=")
        vals = [*vals[:2], pitch, *vals[3:]]
    if css and feats:
        raise ValueError(f"cut {text!r}: a facing pass (css=) takes no step=, flat= or groove=")
    c = Cut(*vals, css_m_min=css, tool=tool, dwell_s=dwell, thread=pitch is not None, **feats)
    if not (60 <= c.rpm <= 20_000 and 0 <= c.depth_mm <= MAX_DEPTH_MM and 0 < c.feed_mm_rev <= 2
            and 0 < c.length_mm <= 1000 and math.isfinite(css)):
        raise ValueError(f"cut {text!r}: outside 60..20000 r/min, 0..{MAX_DEPTH_MM:g} mm deep, "
                         "0..2 mm/rev, 0..1000 mm long")
    for at, what in ((c.step_at_mm, "step="), (c.flat_at_mm, "flat="), (c.groove_at_mm, "groove=")):
        if not 0 <= at < c.length_mm:
            raise ValueError(f"cut {text!r}: {what} at {at:g} mm is outside the pass's 0..{c.length_mm:g} mm")
    if c.step_depth_mm is not None and not 0 < c.step_depth_mm <= MAX_DEPTH_MM:
        raise ValueError(f"cut {text!r}: step= takes a depth of 0..{MAX_DEPTH_MM:g} mm")
    if css and not (10 <= css <= 2000 and c.length_mm < c.diameter_mm / 2):
        raise ValueError(f"cut {text!r}: a facing pass needs css 10..2000 m/min and a radial length "
                         f"under the bar's radius ({c.diameter_mm / 2:g} mm)")
    return c


def _feature(text: str, key: str, value: str) -> dict:
    """step=DEPTH_MM@MM, flat=DEG[@MM], groove=MM+WIDTH_MM as the Cut's fields."""
    forms = {"step": "DEPTH_MM@MM", "flat": "DEG[@MM]", "groove": "MM+WIDTH_MM"}
    first, has, second = value.partition("+" if key == "groove" else "@")
    try:
        a = float(first)
        b = float(second) if has else None
    except ValueError:
        raise ValueError(f"cut {text!r}: {key}= takes {forms[key]} as numbers") from None
    if (b is None and key != "flat") or not math.isfinite(a) or (b is not None and not math.isfinite(b)):
        raise ValueError(f"cut {text!r}: {key}= takes {forms[key]}")
    if key == "step":
        return {"step_depth_mm": a, "step_at_mm": b}
    if key == "flat":
        if not 0 < a < 180:
            raise ValueError(f"cut {text!r}: flat= takes 0..180 degrees of a revolution")
        return {"flat_deg": a, "flat_at_mm": b or 0.0}
    if not 0 < b <= 100:
        raise ValueError(f"cut {text!r}: groove= takes a width of 0..100 mm")
    return {"groove_at_mm": a, "groove_width_mm": b}
