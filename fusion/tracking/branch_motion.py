"""Offline, the choice between rival startup branches by the motion that follows the still
window (:func:`branch_by_motion`): each candidate seeds a tracker, and the readings of the
next seconds say which one the arm is on."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from armfusion.fusion.startup.results import StartupResult
from armfusion.fusion.startup.settings import StartupSettings
from armfusion.models.rotations import DEG
from armfusion.sensors.samples import Recording


def branch_by_motion(startup: StartupResult, tracker_from, rec: Recording, t0_s: float,
                     horizon_s: float, startup_settings: StartupSettings | None = None,
                     decisive_nis: float = 50.0) -> tuple[StartupResult | None, str]:
    """The candidate branch the motion after a still window favours, offline.

    Twins that read the same still read differently once the arm or the chair moves (as a
    disambiguating move makes them). Each candidate of ``startup`` seeds a tracker, run over
    ``horizon_s`` of the recording after ``t0_s``; the link accelerometers' normalised
    innovations (NIS) summed over that stretch are the evidence. A candidate is chosen when
    it beats every other by ``decisive_nis`` (a log-likelihood ratio of 25); it is then a
    startup with those joints numbered (the candidate's own covariance), and the note says
    so. Otherwise ``None``: the joints stay ``ambiguous``. ``tracker_from(result)``: a
    tracker started on a startup result, primed with the recording up to its start."""
    st = startup_settings or StartupSettings()
    n = len(startup.joints)
    amb = [j for j, je in enumerate(startup.joints) if je.flag == "ambiguous"]
    names = ", ".join(startup.joints[j].name for j in amb)
    covs = (startup.candidates_covariance if startup.candidates_covariance is not None
            else np.repeat(np.asarray(startup.covariance)[None], len(startup.candidates_rad), 0))
    window = rec.between(-np.inf, t0_s + horizon_s)
    totals, variants = [], []
    for cand, cov in zip(startup.candidates_rad, covs, strict=True):
        sig = np.sqrt(np.clip(np.diag(cov)[:n], 0, None))
        joints = tuple(
            replace(je, angle_rad=float(cand[j]), sigma_rad=float(sig[j]), alternatives_rad=(),
                    flag="ok" if sig[j] <= st.sigma_limit_deg * DEG else "ill_conditioned")
            if j in amb else je for j, je in enumerate(startup.joints))
        v = replace(startup, joints=joints, q_rad=np.array(cand, float), covariance=np.array(cov),
                    candidates_rad=np.array(cand, float)[None], candidates_covariance=np.array(cov)[None],
                    disambiguating_move=None)
        tr = tracker_from(v)
        tr.run(window, truth=False)
        total = 0.0
        for s_ in tr.link_names:
            lg = tr.innovations(s_)
            ok = np.isfinite(lg.nis) & (lg.t_s > t0_s)
            total += float(np.sum(lg.nis[ok]))
        totals.append(total)
        variants.append(v)
    order = np.argsort(totals)
    best, second = totals[order[0]], totals[order[1]]
    if second - best >= decisive_nis:
        return variants[order[0]], (
            f"{names}: the branch chosen by the motion after the still window (the candidates' "
            f"summed NIS over {horizon_s:g} s: {best:.0f} against {second:.0f} at the next)")
    return None, (f"{names}: ambiguous, and the motion after the still window does not tell the "
                  f"branches apart (summed NIS over {horizon_s:g} s: {best:.0f} and {second:.0f})")
