"""The warm-up a node runs before it takes samples in compiles every signature the live
path then uses: nothing is compiled while samples queue up."""

from __future__ import annotations

import numba
import numpy as np
from armfusion.fusion.tracking import frame_kernels, process_kernels, tracker_kernels, ukf_kernels
from armfusion.fusion.tracking.tracker import StartOptions, start_from_recording, warm_up
from armfusion.models.simulator import simulate


def _signatures() -> dict[str, int]:
    out = {}
    for mod in (process_kernels, tracker_kernels, ukf_kernels, frame_kernels):
        for name in dir(mod):
            f = getattr(mod, name)
            if isinstance(f, numba.core.registry.CPUDispatcher):
                out[f"{mod.__name__}.{name}"] = len(f.signatures)
    return out


def test_the_warm_up_compiles_what_the_live_path_uses(wmra):
    assert warm_up(wmra) > 0.0
    before = _signatures()
    assert sum(before.values()) >= 8  # the models, the filter's stages, the frame, the fits
    # another arm state, another scene, sample by sample as a node fuses them
    rec, _ = simulate(wmra, "static-poses", 6.0, seed=3)
    tr, _ = start_from_recording(wmra, rec, options=StartOptions(propose_unlock=False))
    names = [s for s in tr.sensor_names if s in rec.streams]
    t = rec.get("enc").t_s
    for i in range(int(np.searchsorted(t, tr.t_s + 1e-9)), len(t)):
        for k, s in enumerate(names):
            tr.update(s, float(t[i]) + 1e-4 * k, rec.get(s).values[i])
        assert tr.update_instant(float(t[i]) + 5e-3, {s: rec.get(s).values[i] for s in names}) is not None
    assert _signatures() == before
