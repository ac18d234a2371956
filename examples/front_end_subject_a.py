"""The image front end on the measured DENSE slice (issue 4): every number of the README's
front-end section comes from this script.

1. Track the borders from subject_a's ``frame_masks`` alone (Eqs. 35-37) and compare the
   tracked displacements with DENSE's at the same points (both measured from frame 0).
2. Does the confidence predict the error? Spearman rank correlations.
3. Fuse: joint EKF (12-region relative material) on the tracked borders alone, and on the
   tracked borders plus mid-wall velocities, scored on the same held-out DENSE points. The
   slice has no phase-contrast acquisition: velocity images are made from DENSE by central
   differences (``frontend.pseudo_phase_contrast``), their LPC from those images.

Run:  python examples/front_end_subject_a.py [--json out/front_end.json] [--figures out/front_end] [--download]
(about 3-5 minutes on 2 cores; ``--max-iterations 1`` for a quicker smoke test, not the README's numbers).
subject_a is not shipped with the package (its source has no licence): it is read from the data
directory ``SFEM_FILTERS_DATA`` (``<folder>/dense/subject_a.npz``) or the download cache, or downloaded
from its original repository with ``--download`` (see ``sfem_filters.datasets``).
"""
import argparse
import json
import os
from dataclasses import replace

from sfem_filters.cardiac import NOMINAL, example_path, frontend, load_sequence
from sfem_filters.imaging import sample_velocity, track_masks
from sfem_filters.imaging.contours import midwall_pixels


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the numbers as JSON")
    ap.add_argument("--figures", help="directory for the figures")
    ap.add_argument("--max-iterations", type=int, default=20, help="Gauss-Newton iterations of the smoother")
    ap.add_argument("--download", action="store_true", help="download subject_a from its original repository "
                                                            "if it is not in the data directory or the cache")
    args = ap.parse_args(argv)

    try:
        seq = load_sequence(example_path(download=args.download))
    except FileNotFoundError as exc:    # not in the data directory nor the cache: the message says how to get it
        raise SystemExit(str(exc)) from None
    seq = frontend.rereference(replace(seq, pixel_spacing=NOMINAL["pixel_spacing"],
                                       frame_interval=NOMINAL["frame_interval"]))
    tracks = track_masks(seq.frame_masks)
    te = frontend.tracking_error(seq, tracks)
    print("1. Border tracking from frame_masks vs DENSE (pixels, frames 1-34, from frame 0)")
    print(f"   tracked points {te['n_points']}; RMSE {te['rmse_px']:.2f} px "
          f"(normal {te['rmse_normal_px']:.2f}, tangential {te['rmse_tangential_px']:.2f})")
    print(f"   DENSE motion of those points: RMS {te['motion_rms_px']:.2f} px "
          f"(normal {te['motion_rms_normal_px']:.2f}, tangential {te['motion_rms_tangential_px']:.2f})")
    print("   per-frame RMSE: " + " ".join(f"{v:.2f}" for v in te["rmse_per_frame_px"]))
    s1, s2 = te["spearman_1_minus_c_vs_step_error"], te["spearman_sigma_vs_error"]
    print(f"2. Spearman rho(1 - c, error of that step) = {s1['rho']:.3f} (p = {s1['p']:.1e}); "
          f"rho(accumulated sigma, error) = {s2['rho']:.3f} (p = {s2['p']:.1e})")

    img, venc = frontend.pseudo_phase_contrast(seq)
    vel = sample_velocity(img, seq.points, venc, seq.pixel_spacing, floor=0.01 * venc)
    fusion = frontend.compare_fusion(seq, tracks, vel, max_iterations=args.max_iterations, progress=True)
    a, b = fusion["borders"], fusion["borders+velocity"]
    print(f"3. Joint smoother, held-out DENSE points ({a['n_heldout']}), beta = 0.03 s:")
    print(f"   tracked borders alone      : RMSE {a['heldout_rmse_px']:.3f} px, NIS/dof {a['nis_mean_over_dof']:.2f}")
    print(f"   + velocity at {b['n_velocity_points']} mid-wall points: RMSE {b['heldout_rmse_px']:.3f} px, "
          f"NIS/dof {b['nis_mean_over_dof']:.2f}")
    report = {"tracking": te, "fusion": fusion, "venc_m_per_s": venc}
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump(report, f, indent=2)
    if args.figures:
        from sfem_filters.plotting import observe_figures
        vel_mid = sample_velocity(img, midwall_pixels(seq.frame_masks[0]), venc, seq.pixel_spacing,
                                  floor=0.01 * venc)
        for p in observe_figures({"tracks": tracks, "masks": seq.frame_masks, "velocity": vel_mid}, args.figures):
            print("wrote", p)
    return report


if __name__ == "__main__":
    main()
