"""Turn the HIL emulator's arrays (``hil.simulate``) into a Recording with its truth.

The emulator already converts its raw register counts to SI in FRD, exactly as the
``gy86`` board profile would; its truth is body -> NED on the same board clock.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .dataset import Recording, TimeCleanup
from .readers._common import clean_stream, make_reference


def from_simulation(sim, name: str = "emulator") -> Recording:
    """``sim``: a ``hil.Recording``. Times are the board's ``time_us``."""
    origin = int(sim.time_us[0])
    t = (np.asarray(sim.time_us, dtype=np.int64) - origin) * 1e-6
    t_clean, (gyr, acc, mag), cleanup = clean_stream(t, np.asarray(sim.gyr, float),
                                                     np.asarray(sim.acc, float),
                                                     np.asarray(sim.mag, float))
    ref = make_reference(t, np.asarray(sim.truth_q, float), "truth", "emulator truth")
    return Recording(path=Path(name), format="emulator", t=t_clean, gyr=gyr, acc=acc, mag=mag,
                     world="NED", body="FRD", source="hil.simulate", reference=ref,
                     cleanup=cleanup if cleanup.dropped else TimeCleanup(kept=len(t_clean)))


def simulate(profile: str = "flight", rate_hz: float = 250.0, duration_s: float = 60.0,
             seed: int = 0) -> Recording:
    """Run the emulator without sockets and return its samples as a Recording."""
    from hil import EmulatorConfig
    from hil import simulate as hil_simulate

    sim = hil_simulate(EmulatorConfig(profile=profile, rate_hz=rate_hz,
                                      duration_s=duration_s, seed=seed))
    return from_simulation(sim, f"emulator-{profile}-seed{seed}")
