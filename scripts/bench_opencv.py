#!/usr/bin/env python3
"""Compare visnav's SURF with OpenCV SIFT and ORB on the same images, in the same run.

Usage: python3 scripts/bench_opencv.py [--runs N] [--image F ...] [--visnav PATH]

1. Installs opencv-python-headless and numpy into a venv under target/opencv-venv (never
   system-wide) and re-executes itself there.
2. Runs `visnav bench surf --json --export-pairs target/surf-pairs` (release build; built with
   `cargo build --release` when the binary is missing) to time SURF and export the quality pairs.
3. Times OpenCV SIFT and ORB detect+compute on the same images (median of N runs, 1 thread and all
   threads) and prints the ratios SURF / SIFT and SURF / ORB.
4. Evaluates the repeatability of SIFT on the exported pairs with the protocol of
   src/vision/eval.rs (circular regions of radius 3 sigma, overlap error < 0.4, common part,
   greedy one-to-one), and re-evaluates the exported SURF keypoints with this Python port as a
   cross-check of the two implementations.
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
VENV = os.path.join(ROOT, "target", "opencv-venv")


def ensure_venv():
    """Re-exec inside target/opencv-venv with OpenCV installed."""
    if os.environ.get("VISNAV_OPENCV_VENV") == "1":
        return
    py = os.path.join(VENV, "bin", "python")
    if not os.path.exists(py):
        print(f"creating {VENV}", file=sys.stderr)
        subprocess.check_call([sys.executable, "-m", "venv", VENV])
    probe = subprocess.run([py, "-c", "import cv2, numpy"], capture_output=True)
    if probe.returncode != 0:
        subprocess.check_call([py, "-m", "pip", "install", "--quiet", "opencv-python-headless", "numpy"])
    env = dict(os.environ, VISNAV_OPENCV_VENV="1")
    os.execve(py, [py, os.path.abspath(__file__)] + sys.argv[1:], env)


def time_cv(fn, img, runs):
    fn(img)  # warm-up
    ts = []
    n = 0
    for _ in range(runs):
        t = time.perf_counter()
        kps, _ = fn(img)
        ts.append((time.perf_counter() - t) * 1e3)
        n = len(kps)
    return statistics.median(ts), n


# --- the evaluation protocol of src/vision/eval.rs ---------------------------------------------

def project(h, x, y):
    u = h[0][0] * x + h[0][1] * y + h[0][2]
    v = h[1][0] * x + h[1][1] * y + h[1][2]
    w = h[2][0] * x + h[2][1] * y + h[2][2]
    if abs(w) < 1e-12:
        return None
    return u / w, v / w


def project_region(h, r):
    x, y, rad = r
    p = project(h, x, y)
    px = project(h, x + 1e-3, y)
    py = project(h, x, y + 1e-3)
    if p is None or px is None or py is None:
        return None
    det = ((px[0] - p[0]) * (py[1] - p[1]) - (py[0] - p[0]) * (px[1] - p[1])) / 1e-6
    return (p[0], p[1], rad * math.sqrt(abs(det)))


def intersection(a, b):
    d = math.hypot(a[0] - b[0], a[1] - b[1])
    r1, r2 = a[2], b[2]
    if d >= r1 + r2:
        return 0.0
    if d <= abs(r1 - r2):
        return math.pi * min(r1, r2) ** 2
    a1 = math.acos(max(-1.0, min(1.0, (d * d + r1 * r1 - r2 * r2) / (2 * d * r1))))
    a2 = math.acos(max(-1.0, min(1.0, (d * d + r2 * r2 - r1 * r1) / (2 * d * r2))))
    return r1 * r1 * (a1 - math.sin(a1) * math.cos(a1)) + r2 * r2 * (a2 - math.sin(a2) * math.cos(a2))


def overlap_error(a, b):
    i = intersection(a, b)
    u = math.pi * (a[2] ** 2 + b[2] ** 2) - i
    return 1.0 if u <= 0 else 1.0 - i / u


def inside(r, w, h):
    return r[0] - r[2] >= -0.5 and r[1] - r[2] >= -0.5 and r[0] + r[2] <= w - 0.5 and r[1] + r[2] <= h - 0.5


def inv3(m):
    import numpy as np
    return np.linalg.inv(np.array(m)).tolist()


def repeatability(r1, r2, h12, size1, size2, max_err=0.4):
    h21 = inv3(h12)
    keep1 = []
    for r in r1:
        if not inside(r, *size1):
            continue
        m = project_region(h12, r)
        if m is not None and inside(m, *size2):
            keep1.append(m)
    keep2 = []
    for r in r2:
        if not inside(r, *size2):
            continue
        m = project_region(h21, r)
        if m is not None and inside(m, *size1):
            keep2.append(r)
    pairs = []
    for i, m in enumerate(keep1):
        for j, b in enumerate(keep2):
            if abs(m[0] - b[0]) > m[2] + b[2] or abs(m[1] - b[1]) > m[2] + b[2]:
                continue
            e = overlap_error(m, b)
            if e < max_err:
                pairs.append((e, i, j))
    pairs.sort()
    u1, u2, n = set(), set(), 0
    for _, i, j in pairs:
        if i not in u1 and j not in u2:
            u1.add(i)
            u2.add(j)
            n += 1
    denom = max(1, min(len(keep1), len(keep2)))
    return n / denom, len(keep1), len(keep2)


def main():
    ensure_venv()
    import cv2

    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=15)
    ap.add_argument("--image", action="append", default=[])
    ap.add_argument("--visnav", default=os.path.join(ROOT, "target", "release", "visnav"))
    args = ap.parse_args()

    if not os.path.exists(args.visnav):
        subprocess.check_call(["cargo", "build", "--release", "--bin", "visnav"], cwd=ROOT)
    pairs_dir = os.path.join(ROOT, "target", "surf-pairs")
    cmd = [args.visnav, "bench", "surf", "--json", "--runs", str(args.runs), "--export-pairs", pairs_dir]
    for im in args.image:
        cmd += ["--image", im]
    out = subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True, text=True).stdout
    surf = json.loads(out)

    images = sorted({t["image"] for t in surf["surf"]}, key=lambda p: [t["image"] for t in surf["surf"]].index(p))
    sift = cv2.SIFT_create()
    orb = cv2.ORB_create(nfeatures=1000)
    all_threads = os.cpu_count() or 1
    print(f"OpenCV {cv2.__version__}; median of {args.runs} runs; detect+describe; ms")
    header = f"{'image':<24} {'thr':>3} {'U-SURF':>8} {'SURF':>8} {'SIFT':>8} {'ORB':>8} {'U-SURF/SIFT':>11} {'SURF/SIFT':>9} {'U-SURF/ORB':>10}  features U-SURF/SURF/SIFT/ORB"
    print(header)
    results = []
    for path in images:
        img = cv2.imread(os.path.join(ROOT, path) if not os.path.isabs(path) else path, cv2.IMREAD_GRAYSCALE)
        if img is None:
            sys.exit(f"{path}: cannot read")
        for threads in (1, all_threads):
            cv2.setNumThreads(threads)
            t_sift, n_sift = time_cv(lambda im: sift.detectAndCompute(im, None), img, args.runs)
            t_orb, n_orb = time_cv(lambda im: orb.detectAndCompute(im, None), img, args.runs)
            su = next(t for t in surf["surf"] if t["image"] == path and t["threads"] == threads and t["mode"] == "upright")
            so = next(t for t in surf["surf"] if t["image"] == path and t["threads"] == threads and t["mode"] == "oriented")
            name = os.path.basename(path)
            print(f"{name:<24} {threads:>3} {su['median_ms']:>8.2f} {so['median_ms']:>8.2f} {t_sift:>8.2f} {t_orb:>8.2f} "
                  f"{su['median_ms'] / t_sift:>11.3f} {so['median_ms'] / t_sift:>9.3f} {su['median_ms'] / t_orb:>10.3f}  "
                  f"{su['features']}/{so['features']}/{n_sift}/{n_orb}")
            results.append(dict(image=name, threads=threads, usurf_ms=su["median_ms"], surf_ms=so["median_ms"],
                                sift_ms=t_sift, orb_ms=t_orb, n_usurf=su["features"], n_sift=n_sift, n_orb=n_orb))

    cv2.setNumThreads(all_threads)
    manifest = json.load(open(os.path.join(pairs_dir, "pairs.json")))
    print()
    print("| change | SURF rep. (Rust) | SURF rep. (Python port) | SIFT rep. | SURF n1 | SIFT n1 |")
    print("|---|---|---|---|---|---|")
    worse = 0
    for p in manifest:
        i1 = cv2.imread(os.path.join(pairs_dir, p["img1"]), cv2.IMREAD_GRAYSCALE)
        i2 = cv2.imread(os.path.join(pairs_dir, p["img2"]), cv2.IMREAD_GRAYSCALE)
        size1 = (i1.shape[1], i1.shape[0])
        size2 = (i2.shape[1], i2.shape[0])
        k1 = sift.detect(i1, None)
        k2 = sift.detect(i2, None)
        # OpenCV SIFT: size = 2 sigma; region radius 3 sigma.
        r1 = [(k.pt[0], k.pt[1], 1.5 * k.size) for k in k1]
        r2 = [(k.pt[0], k.pt[1], 1.5 * k.size) for k in k2]
        rep_sift, n1s, _ = repeatability(r1, r2, p["h12"], size1, size2)
        s1 = [(x, y, 3.0 * s) for x, y, s in p["surf_kp1"]]
        s2 = [(x, y, 3.0 * s) for x, y, s in p["surf_kp2"]]
        rep_surf_py, n1, _ = repeatability(s1, s2, p["h12"], size1, size2)
        if p["surf_repeatability"] < rep_sift:
            worse += 1
        print(f"| {p['label']} | {p['surf_repeatability']:.3f} | {rep_surf_py:.3f} | {rep_sift:.3f} | {n1} | {n1s} |")
    print(f"\nSURF repeatability below SIFT's on {worse} of {len(manifest)} pairs")


if __name__ == "__main__":
    main()
