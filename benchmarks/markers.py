"""Colour-marker detection: milliseconds per 640x480 image on one core.

    python benchmarks/markers.py [--images 20] [--repeat 20]

Also measured by `benchmarks/run.py` (which imports `measure`).

Rendered images (jaxloc's own renderer: blur, sensor noise, lighting change, 4 distractor
blobs each) of the overhead camera (three markers) and of an omnidirectional camera (two
markers, annulus mask). OpenCV is limited to one thread. Prints the median time per image
of `jaxloc._vision.markers.detect_markers` (the paper reports 12 ms per 640x480 image; the issue's
target is <= 2 ms), and the detection error against the rendered centroids, so speed is
never bought with accuracy. The sphere-centre correction of the front end is timed apart
(it goes through the JAX camera model).
"""

import argparse
import json
import math
import time

import cv2
import jax.random as jr
import jaxloc
import numpy as np
from jaxloc._vision.markers import annulus_mask, DEFAULT_MARKER_COLORS, detect_markers
from jaxloc._vision.render import (
    annulus_of,
    DEFAULT_MARKER_BGR,
    render_markers,
    sphere_center_pixel,
)


def measure(images: int = 20, repeat: int = 20, verbose: bool = True) -> dict:
    """Median / p90 ms per image of `detect_markers` and centroid errors, per case."""
    cv2.setNumThreads(1)
    rng = np.random.default_rng(0)
    colors = {"C1": DEFAULT_MARKER_COLORS["red"], "C2": DEFAULT_MARKER_COLORS["green"],
              "C3": DEFAULT_MARKER_COLORS["blue"]}  # fmt: skip
    over, omni = jaxloc.paper_overhead_camera(), jaxloc.paper_omni_camera()
    omni_mask = annulus_mask(omni.image_size, annulus_of(omni, 3.0))
    cases = {"overhead (3 markers)": [], "omni (2 markers, annulus)": []}
    for s in range(images):
        while True:  # markers apart (touching markers occlude each other: not a centroid test)
            pts = np.stack(
                [rng.uniform(-1, 1, 3), rng.uniform(-0.7, 0.7, 3), rng.uniform(2.8, 3.6, 3)], -1
            )
            uv = pts[:, :2] / pts[:, 2:]
            if min(np.linalg.norm(uv[i] - uv[j]) for i, j in ((0, 1), (0, 2), (1, 2))) > 0.06:
                break
        img, truth = render_markers(over, pts, key=jr.key(s), names=["C1", "C2", "C3"])
        cases["overhead (3 markers)"].append((img, truth, colors, None))
        az = rng.uniform(0, 2 * math.pi) + np.array([0.0, math.pi * rng.uniform(0.5, 1.5)])
        d = rng.uniform(1.2, 2.5, 2)
        p = np.stack([d * np.cos(az), d * np.sin(az), rng.uniform(-0.1, 0.1, 2)], -1)
        two = [DEFAULT_MARKER_BGR[0], DEFAULT_MARKER_BGR[2]]
        img, truth = render_markers(omni, p, key=jr.key(1000 + s), names=["C1", "C3"], colors=two)
        cases["omni (2 markers, annulus)"].append(
            (img, truth, {"C1": colors["C1"], "C3": colors["C3"]}, omni_mask)
        )
    report = {"images": images, "repeat": repeat, "opencv_threads": 1}
    if verbose:
        print(f"Marker detection, 640x480, one OpenCV thread, {images} images x {repeat}")
    for name, items in cases.items():
        times, errs = [], []
        for img, truth, cols, mask in items:
            det = detect_markers(img, cols, mask=mask)
            for t in truth:
                if t["visible"] and not t["truncated"]:
                    errs.append(np.linalg.norm(det[t["name"]].pixel - t["centroid_px"]))
            t0 = time.perf_counter()
            for _ in range(repeat):
                detect_markers(img, cols, mask=mask)
            times.append((time.perf_counter() - t0) / repeat * 1e3)
        errs = np.asarray(errs)
        med = float(np.median(times))
        p90 = float(np.percentile(times, 90))
        rms, mx = float(np.sqrt(np.mean(errs**2))), float(errs.max())
        report[name] = {"ms_per_image_median": med, "ms_per_image_p90": p90,
                        "error_px_rms": rms, "error_px_max": mx}  # fmt: skip
        if verbose:
            print(f"  {name:<28} {med:6.2f} ms/image (p90 {p90:.2f}); "
                  f"centroid error RMS {rms:.3f} px, max {mx:.3f} px")
    # Sphere-centre correction (front end), per detection, after warm-up.
    img, truth, cols, _ = cases["overhead (3 markers)"][0]
    det = detect_markers(img, cols)
    d = det["C1"]
    sphere_center_pixel(over, d.pixel, d.area)
    t0 = time.perf_counter()
    for _ in range(repeat):
        sphere_center_pixel(over, d.pixel, d.area)
    ms = (time.perf_counter() - t0) / repeat * 1e3
    report["sphere_center_pixel_ms_per_marker"] = ms
    if verbose:
        print(f"  sphere-centre correction (front end, JAX camera model): {ms:.2f} ms per marker")
    return report


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--json", metavar="FILE")
    args = ap.parse_args(argv)
    report = measure(args.images, args.repeat)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
