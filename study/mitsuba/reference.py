#!/usr/bin/env python3
"""Reference images for `vlf study`, rendered by Mitsuba 3 (path tracing).

`vlf study` exports the scene it measures as JSON (format
`vlf-reference-scene/1`: the imported polygons as triangles in scene units,
grouped by material, and the camera) and runs this script, so both renderers
see exactly the same geometry. Materials map one to one:

* diffuse (Kd)         -> `diffuse` (one-sided, like the field)
* mirror (illum 3, Ks) -> `conductor` with `material: none` and
                          `specular_reflectance` = Ks
* both                 -> `blendbsdf` of the two, weights keeping ρd and ρs
* emitter (Ke)         -> `area` light of radiance Ke (front side only)

The camera is a pinhole `perspective` sensor with the same vertical field of
view (`fov_axis: y`), a box pixel filter (the field's renderer averages a
regular grid of samples over each pixel), rendered by the `path` integrator
without a depth limit in practice (`max_depth` 256; Russian roulette from
depth 8 keeps it unbiased).

The reference is the mean of two renders of spp/2 samples with different
seeds (both written, `half-1.pfm` and `half-2.pfm`); half their difference
estimates the reference's own noise, reported here over all pixels as a
relative RMSE (`noise`) and measured again by the study over the pixels it
compares, so it can say how far below the measured errors it is. With `--ladder`, further single renders at the given
sample counts are timed for the equal-quality comparison.

Output: the PFM image (`--out`) and a JSON report on stdout.
"""

import argparse
import json
import os
import struct
import sys
import tempfile
import time

import numpy as np


def write_pfm(path, image):
    """Linear float RGB PFM, little-endian, rows bottom to top."""
    h, w, _ = image.shape
    with open(path, "wb") as f:
        f.write(f"PF\n{w} {h}\n-1.0\n".encode("ascii"))
        f.write(np.ascontiguousarray(image[::-1], dtype="<f4").tobytes())


def write_ply(path, positions, triangles):
    """Binary little-endian PLY with positions and triangle indices only."""
    with open(path, "wb") as f:
        f.write(
            (
                "ply\nformat binary_little_endian 1.0\n"
                f"element vertex {len(positions)}\n"
                "property float x\nproperty float y\nproperty float z\n"
                f"element face {len(triangles)}\n"
                "property list uchar int vertex_indices\nend_header\n"
            ).encode("ascii")
        )
        for p in positions:
            f.write(struct.pack("<3f", *p))
        for t in triangles:
            f.write(struct.pack("<B3i", 3, *t))


def bsdf_of(mesh):
    kd, ks = mesh["diffuse"], mesh["specular"]
    diffuse = {"type": "diffuse", "reflectance": {"type": "rgb", "value": kd}}
    if max(ks) <= 0.0:
        return diffuse
    if max(kd) <= 0.0:
        return {
            "type": "conductor",
            "material": "none",
            "specular_reflectance": {"type": "rgb", "value": ks},
        }
    # weight·conductor + (1 − weight)·diffuse, each scaled back up.
    t = max(ks) / (max(kd) + max(ks))
    return {
        "type": "blendbsdf",
        "weight": t,
        "bsdf_0": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [min(1.0, c / (1 - t)) for c in kd]}},
        "bsdf_1": {
            "type": "conductor",
            "material": "none",
            "specular_reflectance": {"type": "rgb", "value": [min(1.0, c / t) for c in ks]},
        },
    }


def scene_dict(mi, desc, folder):
    cam = desc["camera"]
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 256, "rr_depth": 8, "hide_emitters": False},
        "sensor": {
            "type": "perspective",
            "fov": cam["fovy"],
            "fov_axis": "y",
            "to_world": mi.ScalarTransform4f().look_at(origin=cam["eye"], target=cam["target"], up=cam["up"]),
            "film": {
                "type": "hdrfilm",
                "width": cam["width"],
                "height": cam["height"],
                "rfilter": {"type": "box"},
                "pixel_format": "rgb",
            },
            "sampler": {"type": "independent", "sample_count": 4},
        },
    }
    for i, mesh in enumerate(desc["meshes"]):
        path = os.path.join(folder, f"mesh{i}.ply")
        write_ply(path, mesh["positions"], mesh["triangles"])
        shape = {"type": "ply", "filename": path, "face_normals": True, "bsdf": bsdf_of(mesh)}
        if max(mesh["emission"]) > 0.0:
            shape["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": mesh["emission"]}}
        scene[f"mesh{i}"] = shape
    return scene


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", help="scene JSON written by vlf study (format vlf-reference-scene/1)")
    parser.add_argument("--out", required=True, help="reference image to write (PFM)")
    parser.add_argument("--spp", type=int, required=True, help="samples per pixel of the reference (even)")
    parser.add_argument("--ladder", default="", help="comma-separated sample counts to time, e.g. 1,4,16")
    parser.add_argument("--ladder-dir", default=None, help="where ladder images go (default: next to --out); the report names them relative to it")
    args = parser.parse_args()

    with open(args.scene) as f:
        desc = json.load(f)
    if desc.get("format") != "vlf-reference-scene/1":
        sys.exit(f"{args.scene}: not a vlf-reference-scene/1 file")
    if args.spp < 2 or args.spp % 2:
        sys.exit(f"--spp must be an even number >= 2, got {args.spp}")

    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    report = {"renderer": f"mitsuba {mi.__version__} scalar_rgb path", "spp": args.spp}
    with tempfile.TemporaryDirectory() as folder:
        started = time.perf_counter()
        scene = mi.load_dict(scene_dict(mi, desc, folder))
        report["load_seconds"] = time.perf_counter() - started

        started = time.perf_counter()
        halves = [np.array(mi.render(scene, spp=args.spp // 2, seed=seed), dtype=np.float64) for seed in (1, 2)]
        report["seconds"] = time.perf_counter() - started
        image = 0.5 * (halves[0] + halves[1])
        mean = float(image.mean())
        # Var(a − b) = 2 σ²_half and σ_full = σ_half / √2, so σ_full = RMS(a − b) / 2.
        report["noise"] = float(np.sqrt(np.mean((halves[0] - halves[1]) ** 2)) / 2.0 / mean) if mean > 0 else None
        report["mean"] = mean
        write_pfm(args.out, image.astype(np.float32))
        # The halves too, so the study can measure the noise over the pixels it compares.
        folder_out = args.ladder_dir or os.path.dirname(os.path.abspath(args.out))
        for k, half in enumerate(halves):
            write_pfm(os.path.join(folder_out, f"half-{k + 1}.pfm"), half.astype(np.float32))

        ladder = [int(s) for s in args.ladder.split(",") if s.strip()]
        report["ladder"] = []
        for i, spp in enumerate(ladder):
            started = time.perf_counter()
            img = np.array(mi.render(scene, spp=spp, seed=100 + i), dtype=np.float32)
            seconds = time.perf_counter() - started
            name = f"ladder-{spp}spp.pfm"
            write_pfm(os.path.join(folder_out, name), img)
            report["ladder"].append({"spp": spp, "seconds": seconds, "path": name})
    json.dump(report, sys.stdout)
    print()


if __name__ == "__main__":
    main()
