"""`n3dmap eval egomotion`: relative pose error of the bundle's egomotion vs ICP and identity baselines
(core.eval.protocols.egomotion: consecutive pairs, TUM RPE on ref0_T_ref1, optional seeded perturbations
for datasets whose camera does not move).
"""

from __future__ import annotations

from core.device import resolve_device
from core.eval.protocols.egomotion import NEEDS, EgomotionEvalConfig, evaluate, summarize
from services.cli.eval import add_eval_parser, iter_records, load_bundle_for_eval
from services.cli.eval_tasks.plots import histograms
from services.reports import Report


def register(kinds) -> None:
    parser = add_eval_parser(kinds, "egomotion", help="egomotion error (rad, deg, m) vs ICP and identity")
    parser.add_argument("--perturb-deg", type=float, default=0.0,
                        help="add a random yaw-heavy rotation up to this many degrees to every pair")
    parser.add_argument("--perturb-m", type=float, default=0.0, help="and a random translation up to this (m)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the perturbations")
    parser.add_argument("--no-icp", action="store_true", help="skip the ICP baseline")
    parser.set_defaults(func=run)


def run(args) -> int:
    device = resolve_device(args.device)
    bundle = load_bundle_for_eval(args.bundle, device, NEEDS, data_dir=args.data)
    config = EgomotionEvalConfig(perturb_deg=args.perturb_deg, perturb_m=args.perturb_m, seed=args.seed,
                                 icp=not args.no_icp)
    result = evaluate(bundle, iter_records(args.data, args.max_records), config, device=device)
    report = Report(kind="egomotion", title="Egomotion evaluation", bundle=args.bundle, data=args.data,
                    settings={"max_records": args.max_records, "perturb_deg": args.perturb_deg,
                              "perturb_m": args.perturb_m, "seed": args.seed, "device": str(device)})
    summary = summarize(result)
    summaries = summary["methods"]
    report.metrics = {"egomotion": summaries, "gt_motion": summary["gt_motion"]}
    pairs = summaries["model"]["pairs"]
    report.text(f"{pairs} frame pairs. Relative pose error err = inv(gt)·est of ref0_T_ref1 (TUM RPE): "
                "rotation = angle of err, translation = ‖t of err‖. Mean ground-truth motion per pair: "
                f"{report.metrics['gt_motion']['rot_deg']:.2f}° and {report.metrics['gt_motion']['trans_m']:.3f} m.")
    report.heading("Errors (mean / median)")
    report.table(["method", "R (rad)", "R (deg)", "t (m)", "R median (deg)", "t median (m)"],
                 [[name, s["rot_err_rad_mean"], s["rot_err_deg_mean"], s["trans_err_m_mean"],
                   s["rot_err_deg_median"], s["trans_err_m_median"]] for name, s in summaries.items()], digits=4)
    report.figure("rotation_error_hist", histograms(
        {n: e["rot_err_deg"].numpy() for n, e in result["methods"].items()}, xlabel="rotation error (deg)",
        title="Rotation error per pair"), "Rotation error per pair")
    report.figure("translation_error_hist", histograms(
        {n: e["trans_err_m"].numpy() for n, e in result["methods"].items()}, xlabel="translation error (m)",
        title="Translation error per pair"), "Translation error per pair")
    out = report.write(args.out)
    s = summaries["model"]
    print(f"egomotion: {pairs} pairs, R {s['rot_err_deg_mean']:.3f}°, t {s['trans_err_m_mean']:.3f} m "
          f"-> {out / 'report.md'}")
    return 0
