#!/usr/bin/env python3
"""Compare visnav's SURF with OpenCV's own (non-free) SURF, and with SIFT and ORB, on the same images.

Usage:
    python3 scripts/compare_opencv_surf.py --python PY [--visnav PATH] [--runs N] [--out DIR]
        [--skip-visnav]

PY is a Python interpreter whose `cv2` has the non-free `xfeatures2d.SURF_create` (an OpenCV built
with opencv_contrib and OPENCV_ENABLE_NONFREE=ON; PyPI's wheels are built without it). This script
does not build or install OpenCV. When SURF is not available it says so and exits with status 2.

1. Runs `visnav bench surf --json --runs N --export-pairs DIR/pairs --export-features DIR/features`
   (release binary; unless --skip-visnav reuses DIR) to time visnav SURF and export, for the two
   bench images and the 21 protocol pairs, keypoints and SURF-64 descriptors.
2. Times OpenCV SURF (same hessianThreshold, nOctaves, nOctaveLayers, extended=False, upright on /
   off), SIFT and ORB (1000) on 1 thread and on all threads (median of N runs).
3. Keypoint agreement per image: fraction of visnav keypoints with an OpenCV keypoint within 1 px
   and a size ratio within 1.2, orientation difference and SURF-64 descriptor distance of those
   pairs (OpenCV's upright descriptor frame is visnav's frame rotated by -90 degrees: its
   subregion rows run along +x and its columns along -y; visnav's U-SURF vectors are permuted into
   it before the distance is taken).
4. Repeatability and matching score on the exported protocol pairs with a Python port of
   src/vision/eval.rs (same images and homographies as the Rust evaluation; visnav's own exported
   keypoints and descriptors are re-scored by the port as a cross-check).
"""
import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def surf_available():
    try:
        import cv2  # noqa: F401
    except ImportError as e:
        return False, f"cannot import cv2 ({e})"
    import cv2
    if not hasattr(cv2, "xfeatures2d"):
        return False, f"cv2 {cv2.__version__} has no xfeatures2d (opencv_contrib not built)"
    try:
        cv2.xfeatures2d.SURF_create(100)
    except cv2.error as e:
        msg = str(e).strip().splitlines()[-1] if str(e).strip() else "error"
        return False, f"cv2 {cv2.__version__}: SURF_create failed (non-free disabled?): {msg}"
    return True, cv2.__version__


def ensure_interpreter(python):
    """Re-exec under `python` unless this interpreter already has non-free SURF."""
    ok, why = surf_available()
    if ok:
        return
    if python and os.path.realpath(python) != os.path.realpath(sys.executable) \
            and os.environ.get("VISNAV_SURF_REEXEC") != "1":
        env = dict(os.environ, VISNAV_SURF_REEXEC="1")
        os.execve(python, [python, os.path.abspath(__file__)] + sys.argv[1:], env)
    print(f"OpenCV SURF is NOT available in {sys.executable}: {why}.\n"
          "Pass --python with an interpreter whose cv2 was built with opencv_contrib and "
          "OPENCV_ENABLE_NONFREE=ON. Nothing was compared.", file=sys.stderr)
    sys.exit(2)


# --- the evaluation protocol of src/vision/eval.rs: shared with bench_opencv.py ---------------

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_opencv import project, project_region, intersection, overlap_error, inside  # noqa: E402,F401


def score(r1, r2, d1, d2, lap1, lap2, h12, size1, size2, metric="l2", max_err=0.4):
    """Repeatability and matching score (eval.rs `score_pair`). r: (x, y, radius) regions;
    d: descriptor arrays (numpy) or None; lap: Laplacian signs or None (no gate)."""
    import numpy as np
    h21 = np.linalg.inv(np.array(h12)).tolist()
    keep1, mapped1 = [], []
    for i, r in enumerate(r1):
        if not inside(r, *size1):
            continue
        m = project_region(h12, r)
        if m is not None and inside(m, *size2):
            keep1.append(i)
            mapped1.append(m)
    keep2 = []
    for j, r in enumerate(r2):
        if not inside(r, *size2):
            continue
        m = project_region(h21, r)
        if m is not None and inside(m, *size1):
            keep2.append(j)
    pairs = []
    if keep1 and keep2:
        bx = np.array([r2[j][0] for j in keep2])
        by = np.array([r2[j][1] for j in keep2])
        br = np.array([r2[j][2] for j in keep2])
        for a, m in zip(keep1, mapped1):
            cand = np.nonzero((np.abs(m[0] - bx) <= m[2] + br) & (np.abs(m[1] - by) <= m[2] + br))[0]
            for c in cand:
                j = keep2[c]
                e = overlap_error(m, r2[j])
                if e < max_err:
                    pairs.append((e, a, j))
    pairs.sort(key=lambda p: p[0])
    u1, u2, corr = set(), set(), set()
    for _, i, j in pairs:
        if i not in u1 and j not in u2:
            u1.add(i)
            u2.add(j)
            corr.add((i, j))
    denom = max(1, min(len(keep1), len(keep2)))
    rep = len(corr) / denom
    if d1 is None or not keep1 or not keep2:
        return rep, None, len(keep1), len(keep2)
    q = d1[keep1]
    t = d2[keep2]
    if metric == "hamming":
        x = np.bitwise_xor(q[:, None, :], t[None, :, :])
        dist = np.unpackbits(x, axis=2).sum(axis=2).astype(np.float64)
    else:
        q64, t64 = q.astype(np.float64), t.astype(np.float64)
        dist = (q64 * q64).sum(1)[:, None] + (t64 * t64).sum(1)[None, :] - 2.0 * q64 @ t64.T
    if lap1 is not None:
        l1 = np.array([lap1[i] for i in keep1])
        l2 = np.array([lap2[j] for j in keep2])
        dist = np.where(l1[:, None] == l2[None, :], dist, np.inf)
    trains = set()
    correct = 0
    for a in range(len(keep1)):
        row = dist[a]
        b = int(np.argmin(row))
        if not np.isfinite(row[b]):
            continue
        i, j = keep1[a], keep2[b]
        ok = (i, j) in corr
        if not ok:
            m = project_region(h12, r1[i])
            ok = m is not None and overlap_error(m, r2[j]) < max_err
        if ok and j not in trains:
            trains.add(j)
            correct += 1
    return rep, correct / denom, len(keep1), len(keep2)


# --- helpers ---------------------------------------------------------------------------------------

def time_cv(fn, img, runs):
    fn(img)  # warm-up
    ts, n = [], 0
    for _ in range(runs):
        t = time.perf_counter()
        kps, _ = fn(img)
        ts.append((time.perf_counter() - t) * 1e3)
        n = len(kps)
    return statistics.median(ts), n


def usurf_to_opencv_frame(d):
    """visnav U-SURF-64 (subregion (row by along +y, col bx along +x), values dx, dy, |dx|, |dy|)
    into OpenCV's upright layout (subregion (row along +x, col along -y), values -dy, dx, |dy|, |dx|)."""
    import numpy as np
    out = np.zeros_like(d)
    for by in range(4):
        for bx in range(4):
            src = d[:, (by * 4 + bx) * 4:(by * 4 + bx) * 4 + 4]
            dst = (bx * 4 + (3 - by)) * 4
            out[:, dst + 0] = -src[:, 1]
            out[:, dst + 1] = src[:, 0]
            out[:, dst + 2] = src[:, 3]
            out[:, dst + 3] = src[:, 2]
    return out


def keypoint_agreement(ours_kp, ours_desc, cv_kps, cv_desc, upright):
    """Match each visnav keypoint to the nearest OpenCV keypoint within 1 px and size ratio 1.2."""
    import numpy as np
    if len(ours_kp) == 0 or len(cv_kps) == 0:
        return None
    cx = np.array([k.pt[0] for k in cv_kps])
    cy = np.array([k.pt[1] for k in cv_kps])
    cs = np.array([k.size for k in cv_kps])
    ca = np.array([k.angle for k in cv_kps])
    cl = np.array([k.class_id for k in cv_kps])
    # Grid of 4 px cells for the neighbour search.
    cells = {}
    for idx, (x, y) in enumerate(zip(cx, cy)):
        cells.setdefault((int(x // 4), int(y // 4)), []).append(idx)
    od = usurf_to_opencv_frame(ours_desc) if upright else ours_desc
    pairs = []
    used_cv = set()
    for i, k in enumerate(ours_kp):
        x, y, size = k[0], k[1], k[2]
        best, bd = None, 1.0
        for gx in range(int(x // 4) - 1, int(x // 4) + 2):
            for gy in range(int(y // 4) - 1, int(y // 4) + 2):
                for j in cells.get((gx, gy), ()):
                    d = math.hypot(cx[j] - x, cy[j] - y)
                    r = max(cs[j], size) / min(cs[j], size)
                    if d <= bd and r <= 1.2:
                        best, bd = j, d
        if best is not None:
            pairs.append((i, best, bd))
            used_cv.add(best)
    if not pairs:
        return dict(n_ours=len(ours_kp), n_cv=len(cv_kps), frac_ours=0.0, frac_cv=0.0)
    ii = np.array([p[0] for p in pairs])
    jj = np.array([p[1] for p in pairs])
    dd = np.array([p[2] for p in pairs])
    ratio = cs[jj] / np.array([ours_kp[i][2] for i in ii])
    lap_ok = np.mean(cl[jj] == np.array([ours_kp[i][5] for i in ii]))
    desc_d = np.linalg.norm(od[ii] - cv_desc[jj], axis=1)
    # Reference: distance of each visnav descriptor to the nearest OpenCV descriptor that is NOT its
    # counterpart (typical distance between different keypoints).
    sample = ii[:: max(1, len(ii) // 300)]
    js = jj[:: max(1, len(ii) // 300)]
    ref = []
    for i, j in zip(sample, js):
        dist = np.linalg.norm(cv_desc - od[i], axis=1)
        dist[j] = np.inf
        ref.append(dist.min())
    res = dict(
        n_ours=len(ours_kp), n_cv=len(cv_kps), frac_ours=len(pairs) / len(ours_kp),
        frac_cv=len(used_cv) / len(cv_kps), median_offset_px=float(np.median(dd)),
        median_size_ratio=float(np.median(ratio)), laplacian_agree=float(lap_ok),
        desc_dist_median=float(np.median(desc_d)), desc_dist_p90=float(np.percentile(desc_d, 90)),
        desc_dist_other_median=float(np.median(ref)),
    )
    if not upright:
        ours_deg = np.degrees(np.array([ours_kp[i][4] for i in ii])) % 360.0
        diff = np.abs((ours_deg - ca[jj] + 180.0) % 360.0 - 180.0)
        res.update(ori_diff_median_deg=float(np.median(diff)), ori_diff_p90_deg=float(np.percentile(diff, 90)),
                   ori_within_5deg=float(np.mean(diff <= 5.0)))
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--python", help="interpreter whose cv2 has non-free xfeatures2d.SURF")
    ap.add_argument("--visnav", default=os.path.join(ROOT, "target", "release", "visnav"))
    ap.add_argument("--runs", type=int, default=15)
    ap.add_argument("--out", default=os.path.join(ROOT, "target", "opencv-surf"))
    ap.add_argument("--skip-visnav", action="store_true", help="reuse DIR from a previous run")
    ap.add_argument("--json", help="also write all results to this JSON file")
    ap.add_argument("--top", type=int, default=0,
                    help="protocol pairs: keep only the N strongest keypoints per image for every "
                         "detector (equal counts; 0 keeps all)")
    ap.add_argument("--pairs-only", action="store_true", help="skip the timing and agreement part")
    args = ap.parse_args()
    ensure_interpreter(args.python)
    import cv2
    import numpy as np

    pairs_dir = os.path.join(args.out, "pairs")
    feat_dir = os.path.join(args.out, "features")
    bench_json = os.path.join(args.out, "bench.json")
    if not args.skip_visnav:
        if not os.path.exists(args.visnav):
            sys.exit(f"{args.visnav}: visnav binary missing (cargo build --release --bin visnav)")
        cmd = [args.visnav, "bench", "surf", "--json", "--runs", str(args.runs),
               "--export-pairs", pairs_dir, "--export-features", feat_dir]
        out = subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True, text=True).stdout
        os.makedirs(args.out, exist_ok=True)
        with open(bench_json, "w") as f:
            f.write(out)
    with open(bench_json) as f:
        bench = json.load(f)
    params = json.load(open(os.path.join(pairs_dir, "pairs.json")))[0]["params"]
    thr, n_oct, n_lay = params["hessian_threshold"], params["n_octaves"], params["n_octave_layers"]
    all_threads = os.cpu_count() or 1
    try:
        load = open("/proc/loadavg").read().split()[:3]
    except OSError:
        load = ["?"]
    results = dict(opencv=cv2.__version__, load_before=load, params=params, timing=[], agreement=[], pairs=[])
    print(f"OpenCV {cv2.__version__} (non-free SURF); visnav params {params}; load average {' '.join(load)}")

    def surf_cv(upright, layers=n_lay):
        return cv2.xfeatures2d.SURF_create(hessianThreshold=thr, nOctaves=n_oct, nOctaveLayers=layers,
                                           extended=False, upright=upright)

    sift = cv2.SIFT_create()
    orb = cv2.ORB_create(nfeatures=1000)

    # --- speed and keypoint agreement on the bench images -------------------------------------
    images = []
    if args.pairs_only:
        bench["surf"] = []
    for t in bench["surf"]:
        if t["image"] not in images:
            images.append(t["image"])
    print("\nmedian ms of detect+describe (features)")
    print(f"{'image':<24} {'thr':>3} {'ours U':>14} {'ours SURF':>14} {'cv U-SURF':>14} {'cv SURF':>14} "
          f"{'cv SURF L3':>14} {'SIFT':>14} {'ORB':>12}")
    for path in images:
        img = cv2.imread(path if os.path.isabs(path) else os.path.join(ROOT, path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            sys.exit(f"{path}: cannot read")
        name = os.path.basename(path)
        for threads in (1, all_threads):
            cv2.setNumThreads(threads)
            row = dict(image=name, threads=threads)
            for key, det in [("cv_usurf", surf_cv(True)), ("cv_surf", surf_cv(False)),
                             ("cv_surf_l3", surf_cv(False, 3)), ("sift", sift), ("orb", orb)]:
                ms, n = time_cv(lambda im: det.detectAndCompute(im, None), img, args.runs)
                row[key] = (ms, n)
            for mode, key in [("upright", "ours_usurf"), ("oriented", "ours_surf")]:
                t = next(t for t in bench["surf"] if t["image"] == path and t["threads"] == threads and t["mode"] == mode)
                row[key] = (t["median_ms"], t["features"])
            results["timing"].append(row)

            def f(k):
                return f"{row[k][0]:7.2f} ({row[k][1]:>5})"
            print(f"{name:<24} {threads:>3} {f('ours_usurf')} {f('ours_surf')} {f('cv_usurf')} {f('cv_surf')} "
                  f"{f('cv_surf_l3')} {f('sift')} {row['orb'][0]:6.2f} ({row['orb'][1]})")
        cv2.setNumThreads(all_threads)
        stem = os.path.splitext(name)[0]
        for mode, upright in [("upright", True), ("oriented", False)]:
            fp = os.path.join(feat_dir, f"{stem}_{mode}.json")
            if not os.path.exists(fp):
                continue
            doc = json.load(open(fp))
            kps, desc = surf_cv(upright).detectAndCompute(img, None)
            ag = keypoint_agreement(doc["keypoints"], np.array(doc["descriptors"], dtype=np.float32), kps, desc, upright)
            ag.update(image=name, mode=mode)
            results["agreement"].append(ag)
    print("\nkeypoint agreement (visnav vs OpenCV SURF, same parameters): within 1 px and size ratio <= 1.2")
    for ag in results["agreement"]:
        extra = ""
        if "ori_diff_median_deg" in ag:
            extra = (f"  orientation diff median {ag['ori_diff_median_deg']:.1f} deg, p90 {ag['ori_diff_p90_deg']:.1f}, "
                     f"within 5 deg {ag['ori_within_5deg']:.2f}")
        print(f"{ag['image']:<24} {ag['mode']:<8} ours {ag['n_ours']:>5} cv {ag['n_cv']:>5}  matched: "
              f"{ag['frac_ours']:.3f} of ours, {ag['frac_cv']:.3f} of cv; offset median {ag.get('median_offset_px', 0):.2f} px, "
              f"size ratio {ag.get('median_size_ratio', 0):.3f}, laplacian agree {ag.get('laplacian_agree', 0):.3f}; "
              f"descriptor L2 median {ag.get('desc_dist_median', 0):.3f} p90 {ag.get('desc_dist_p90', 0):.3f} "
              f"(nearest other {ag.get('desc_dist_other_median', 0):.3f}){extra}")

    # --- protocol pairs -------------------------------------------------------------------------
    manifest = json.load(open(os.path.join(pairs_dir, "pairs.json")))
    print("\n| change | rep. ours | rep. ours (port) | rep. cv SURF | rep. SIFT | rep. ORB | MS ours SURF | MS ours (port) "
          "| MS cv SURF | MS ours U-SURF | MS cv U-SURF | MS SIFT | MS ORB | n1 ours / cv / SIFT |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    cv_u, cv_o = surf_cv(True), surf_cv(False)
    for i, p in enumerate(manifest):
        i1 = cv2.imread(os.path.join(pairs_dir, p["img1"]), cv2.IMREAD_GRAYSCALE)
        i2 = cv2.imread(os.path.join(pairs_dir, p["img2"]), cv2.IMREAD_GRAYSCALE)
        s1, s2 = (i1.shape[1], i1.shape[0]), (i2.shape[1], i2.shape[0])
        h = p["h12"]

        def load_desc(tag, k):
            return np.fromfile(os.path.join(pairs_dir, f"pair{i:02}_{k}_{tag}.f32"), dtype="<f4").reshape(-1, 64)

        def strongest(kps, desc, resp):
            if args.top <= 0 or len(kps) <= args.top:
                return kps, desc
            order = sorted(range(len(kps)), key=lambda i: -resp(kps[i]))[:args.top]
            return [kps[i] for i in order], (desc[order] if desc is not None else None)

        reg = lambda kps: [(k[0], k[1], 3.0 * k[3]) for k in kps]  # noqa: E731
        lap = lambda kps: [int(k[5]) for k in kps]  # noqa: E731
        o1, d1o = strongest(p["surf_keypoints1"], load_desc("surf64", 1), lambda k: k[6])
        o2, d2o = strongest(p["surf_keypoints2"], load_desc("surf64", 2), lambda k: k[6])
        rep_o, ms_o, n1o, _ = score(reg(o1), reg(o2), d1o, d2o, lap(o1), lap(o2), h, s1, s2)
        u1, d1u = strongest(p["usurf_keypoints1"], load_desc("usurf64", 1), lambda k: k[6])
        u2, d2u = strongest(p["usurf_keypoints2"], load_desc("usurf64", 2), lambda k: k[6])
        _, ms_ou, _, _ = score(reg(u1), reg(u2), d1u, d2u, lap(u1), lap(u2), h, s1, s2)
        if args.top > 0:
            # The Rust figures use all keypoints; show the port's equal-count figures instead.
            p["surf_repeatability"], p["surf_matching_score"], p["usurf_matching_score"] = rep_o, ms_o, ms_ou

        def cv_score(det, metric="l2", radius=lambda k: 3.0 * k.size * 1.2 / 9.0, gate=True):
            k1, d1 = det.detectAndCompute(i1, None)
            k2, d2 = det.detectAndCompute(i2, None)
            if d1 is None or d2 is None:
                return 0.0, 0.0, 0
            k1, d1 = strongest(list(k1), d1, lambda k: k.response)
            k2, d2 = strongest(list(k2), d2, lambda k: k.response)
            r1 = [(k.pt[0], k.pt[1], radius(k)) for k in k1]
            r2 = [(k.pt[0], k.pt[1], radius(k)) for k in k2]
            l1 = [k.class_id for k in k1] if gate else None
            l2 = [k.class_id for k in k2] if gate else None
            rep, ms, n1, _ = score(r1, r2, d1, d2, l1, l2, h, s1, s2, metric)
            return rep, ms, n1

        rep_c, ms_c, n1c = cv_score(cv_o)
        _, ms_cu, _ = cv_score(cv_u)
        # SIFT: size = 2 sigma, region radius 3 sigma; no Laplacian gate.
        rep_s, ms_s, n1s = cv_score(sift, radius=lambda k: 1.5 * k.size, gate=False)
        # ORB: no scale sigma; the region is its described patch (radius size/2). Not strictly comparable.
        rep_b, ms_b, _ = cv_score(orb, metric="hamming", radius=lambda k: 0.5 * k.size, gate=False)
        row = dict(change=p["label"], rep_ours=p["surf_repeatability"], rep_ours_port=rep_o, rep_cv=rep_c,
                   rep_sift=rep_s, rep_orb=rep_b, ms_ours=p.get("surf_matching_score"), ms_ours_port=ms_o,
                   ms_cv=ms_c, ms_ours_usurf=p.get("usurf_matching_score"), ms_ours_usurf_port=ms_ou,
                   ms_cv_usurf=ms_cu, ms_sift=ms_s, ms_orb=ms_b, n1_ours=n1o, n1_cv=n1c, n1_sift=n1s)
        results["pairs"].append(row)
        print(f"| {p['label']} | {row['rep_ours']:.3f} | {rep_o:.3f} | {rep_c:.3f} | {rep_s:.3f} | {rep_b:.3f} | "
              f"{row['ms_ours']:.3f} | {ms_o:.3f} | {ms_c:.3f} | {row['ms_ours_usurf']:.3f} | {ms_cu:.3f} | "
              f"{ms_s:.3f} | {ms_b:.3f} | {n1o} / {n1c} / {n1s} |")
    rows = results["pairs"]
    print(f"\nrepeatability: ours below SIFT on {sum(r['rep_ours'] < r['rep_sift'] for r in rows)} of {len(rows)}, "
          f"OpenCV SURF below SIFT on {sum(r['rep_cv'] < r['rep_sift'] for r in rows)}, "
          f"ours below OpenCV SURF on {sum(r['rep_ours'] < r['rep_cv'] for r in rows)}")
    try:
        results["load_after"] = open("/proc/loadavg").read().split()[:3]
    except OSError:
        pass
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1, default=float)


if __name__ == "__main__":
    main()
