"""The diagnosis's verdict and its final record, from where its rounds ended (the state of
:func:`identify.diagnosis.rounds.diagnose`: its options, rounds, named effects, confounded
groups, current model and last measurement)."""

from __future__ import annotations

from identify.diagnosis.regime_notes import regime_left_note
from identify.diagnosis.scores import evidence_of
from identify.diagnosis.selection import at_noise, gap_ratio
from identify.model.effects import get_effect

__all__ = ["verdict", "final_record"]


def verdict(st, where_final: list, regime_final) -> tuple[str, float]:
    """``adequate`` or ``unexplained``, with its reasons added to the notes; and the final
    model's held-out gap over the noise floor."""
    opts, notes, final_res = st.opts, st.notes, st.final_res
    regime_left = bool(regime_final is not None and regime_final.mismatched)
    n_feat = max(len(where_final), 1)
    misfit_left = [m for m in where_final if m.p_value < opts.alpha / n_feat]
    # significant candidates that would close a real part of the gap but could not be
    # named (no convergence, a confounded group): the gap is then not explained. One that
    # is formally significant but closes little is the encoding's own misfit, not evidence.
    # (the final round's record of the named model itself has effect None: not a candidate)
    # (nor is one whose estimate its own interval does not tell from the null: no evidence)
    still = [c for c in (st.rounds[-1] if st.rounds else []) if c.effect is not None
             and c.significant and not c.named and c.effect not in st.effects
             and not c.confounded_with and not c.undetermined and (c.closes or c.heldout_error)]
    grouped = {e for g in st.confounded if g.get("closes") for e in g["effects"]}
    measured = final_res is not None and final_res.ok
    ratio = gap_ratio(final_res) if measured else float("nan")
    within = at_noise(final_res, opts) if measured else False
    # within the tolerance there is no gap left for an unnamed candidate to explain
    if (within or (not misfit_left and not still and not grouped)) and not regime_left:
        if misfit_left or still:
            notes.append(f"adequate: the held-out gap is {ratio:.2f}× the noise floor (tolerance "
                         f"{opts.gap_tolerance:g}×, the encoding's own error on model-made data), though "
                         + ", ".join([f"{m.feature} ({m.misfit_sigma:.1f} σ)" for m in misfit_left]
                                     + [f"candidate {c.effect} ({evidence_of(c)})" for c in still])
                         + " are significant")
        return "adequate", ratio
    if misfit_left:
        notes.append(f"misfit left (held-out gap {ratio:.2f}× the noise floor) in: "
                     + ", ".join(f"{m.feature} ({m.misfit_sigma:.1f} σ)" for m in misfit_left))
    if still:
        notes.append("significant but not named: " + ", ".join(
            f"{c.effect} ({c.note})" for c in still))
    if grouped:
        notes.append("the gap is closed by candidates the data cannot tell apart: "
                     + "; ".join(" | ".join(g["effects"]) for g in st.confounded))
    if regime_left:
        notes.append(regime_left_note(regime_final, st.rounds, st.effects))
    return "unexplained", ratio


def final_record(st, ok: bool, ratio: float, profile: dict | None) -> dict:
    """The final model's law, free values and gaps, as the result's ``final``."""
    final_res, current = st.final_res, st.current
    # with the values a named effect sets without fitting them (the rough track's period:
    # its coefficients mean nothing without it)
    set_by = {n for e in st.effects for n in get_effect(e).sets}
    final = dict(law=current["law"], free=list(current["free"]),
                 values={n: current["values"][n] for n in (*current["free"], *sorted(set_by))
                         if n in current["values"]},
                 gap_um=final_res.gap["gap_um"] if ok else float("nan"),
                 heldout_gap_um=final_res.heldout["gap_um"] if ok else float("nan"),
                 noise_um=final_res.gap["noise_um"] if ok else float("nan"))
    final["heldout_gap_ratio"] = float(ratio)
    if profile is not None and profile.get("named"):
        # named by its profile: the runs fitted at its best point; held out, the runs left
        # out for their regime (the refits' held-out folds never had it)
        final.update(gap_um=profile["gap_after_um"], heldout_gap_um=float("nan"), heldout_gap_ratio=float("nan"),
                     regime_slip_gap_before_um=profile["slip_gap_before_um"],
                     regime_slip_gap_after_um=profile["slip_gap_after_um"],
                     regime_slip_gap_heldout_um=profile["slip_gap_heldout_um"])
    return final
