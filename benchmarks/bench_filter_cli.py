"""Benchmark of the whole ``probegrid filter`` command against Filament's ``cmgen`` (not a test).

For each HDR in ``tests/data/hdr`` it prints, in one run:

* **Times.** The whole ``probegrid filter HDR --out DIR --size 128`` process (32^2 exact
  diffuse, the full GGX chain 128 -> 1, SH, DFG table, previews; wall and peak RSS from
  ``/usr/bin/time``) with each stage from its manifest (the rest is interpreter start-up and
  imports), next to cmgen's three runs on the same file: ``cmgen --no-mirror -s 128
  --ibl-ld=DIR``, ``cmgen --no-mirror -s 32 --ibl-irradiance=DIR`` and ``cmgen --no-mirror
  --sh=3`` (float32 PSD output, ``-f psd -c 32``, so that its maps can be scored; its defaults
  otherwise: 1024 samples, levels down to 16^2). Best of ``--repeat`` interleaved runs; the
  target is probegrid <= 0.5 x cmgen's summed time. The DFG table comes from the user cache
  (filled by the first run, see probegrid.usercache).
* **Errors against a converged reference.** Diffuse: the exact clamped-cosine sum over a 512^2
  cube of the input (:func:`probegrid.core.diffuse.diffuse_exact`), 32^2; scored: probegrid's map
  (the same functions the command runs) and cmgen's irradiance map (cmgen writes its cube from a
  lat-long in another orientation: the cube symmetry that maps its level 0 onto probegrid's is
  found and undone; its map holds irradiance / pi like ours, checked by the ratio printed).
  GGX: at up to 1024 random texels of each level, the dense normalised GGX sum over a 256^2 cube
  of the input (the reference), probegrid's chain, cmgen's levels (at the roughness cmgen
  prints for them) and the *source floor*: the same dense sum over probegrid's own 128^2 cube,
  i.e. the best any filter of that cube can do. Target: probegrid within 2x of the floor.
  RMS and max of the per-texel, per-channel relative error.
* **SH diffuse at 3, 5, 7, 9 bands** against the same diffuse reference, beside the best that
  band count allows (:func:`probegrid.core.sh.project_equirect` of every input pixel).

Last, a large input: one of the HDRs resampled to 1500 x 750 and filtered with every default,
against targets of 5 s and 500 MB peak RSS, beside cmgen at 256^2 on the same file.

References are cached on disk (``--cache``). Usage::

    .venv/bin/python benchmarks/bench_filter_cli.py [--repeat 3] [--hdr venice studio] [--no-bytecode]

probegrid runs with its modules' bytecode cached, as an installed package has it: a
``PYTHONDONTWRITEBYTECODE`` in the environment (this development machine sets one) is left out
of the runs' environment, so the warm-up run writes ``__pycache__`` and the timed runs read it.
``--no-bytecode`` keeps the environment as it is (each run then compiles the ~27 modules the
filter loads: about 0.07 s CPU, 0.03-0.05 s wall).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from probegrid.core import lobes, sh
from probegrid.core.cubemap import symmetry_permutations, texel_directions, texel_solid_angles
from probegrid.core.diffuse import diffuse_exact, diffuse_sh
from probegrid.core.layouts import to_cube
from probegrid.core.specular import ZonalOutput, symmetric_zonal_sums

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "tests" / "data" / "hdr"
FACES = ("px", "nx", "py", "ny", "pz", "nz")
CMGEN = shutil.which("cmgen") or "/usr/bin/cmgen"
PROBEGRID = str(Path(sys.executable).with_name("probegrid"))


def read_rgb(path: Path) -> np.ndarray:
    buf = oiio.ImageBuf(str(path))
    if buf.has_error:
        raise RuntimeError(buf.geterror())
    return np.asarray(buf.get_pixels(oiio.FLOAT), dtype=np.float32)[..., :3]


def timed(cmd: list[str], env: dict[str, str] | None = None) -> tuple[float, float, float]:
    """Wall seconds, peak RSS (MB) and CPU seconds (user + system) of a command, from
    /usr/bin/time (CPU time is the figure to trust on a loaded machine)."""
    res = subprocess.run(["/usr/bin/time", "-f", "%e %M %U %S", *cmd], capture_output=True,
                         text=True, check=True, env=env)
    wall, rss, user, system = res.stderr.strip().splitlines()[-1].split()
    return float(wall), float(rss) / 1024, float(user) + float(system)


def cached(cache: Path, key: str, compute):
    path = cache / f"{hashlib.sha1(key.encode()).hexdigest()[:20]}.npy"
    if path.exists():
        return np.load(path)
    val = compute()
    np.save(path, val)
    return val


def dense_ggx_at(cube: np.ndarray, dirs: np.ndarray, alpha: float) -> np.ndarray:
    """Normalised GGX sum over every texel of ``cube`` at the directions ``dirs`` (float64)."""
    n = cube.shape[1]
    w = texel_directions(n).reshape(-1, 3)
    lw = np.concatenate([cube.reshape(-1, 3).astype(np.float64),
                         np.ones((w.shape[0], 1))], 1) * texel_solid_angles(n).reshape(-1, 1)
    out = np.empty((len(dirs), 3))
    for i in range(0, len(dirs), 64):
        k = lobes.ggx_kernel_inplace(dirs[i:i + 64] @ w.T, alpha) @ lw
        out[i:i + 64] = k[:, :3] / k[:, 3:]
    return out


def errors(x: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    e = np.abs(x.astype(np.float64) - ref) / np.abs(ref)
    return float(np.sqrt(np.mean(e**2))), float(e.max())


def to_ours(theirs: np.ndarray, k: int) -> np.ndarray:
    """cmgen's cube in probegrid's orientation: ours[perm[k, q]] = theirs[q]."""
    n = theirs.shape[1]
    flat = theirs.reshape(-1, 3)
    out = np.empty_like(flat)
    out[symmetry_permutations(n)[k]] = flat
    return out.reshape(theirs.shape)


def bench(name: str, hdr: Path, work: Path, cache: Path, args: argparse.Namespace) -> dict:
    img = read_rgb(hdr)
    print(f"\n===== {name}: {hdr.name} ({img.shape[1]}x{img.shape[0]}) =====")
    # ---------------- times ----------------
    out = work / "pg"
    runs: dict[str, list] = {"pg": [], "ld": [], "irr": [], "sh": []}
    stages: list[dict] = []
    env = None
    if not args.no_bytecode:  # probegrid's modules from cached bytecode, as installed
        env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    subprocess.run([PROBEGRID, "filter", str(hdr), "--out", str(out), "--size", "128"],
                   check=True, capture_output=True, env=env)  # fills the user cache (DFG) once
    for _ in range(args.repeat):
        shutil.rmtree(out, ignore_errors=True)
        runs["pg"].append(timed([PROBEGRID, "filter", str(hdr), "--out", str(out), "--size",
                                 "128"], env))
        stages.append(json.loads((out / "manifest.json").read_text())["timings_s"])
        for tag, extra in (("ld", ["-s", "128", f"--ibl-ld={work / 'ld'}"]),
                           ("irr", ["-s", "32", f"--ibl-irradiance={work / 'irr'}"]),
                           ("sh", ["--sh=3", f"--sh-output={work / 'sh.txt'}"])):
            runs[tag].append(timed([CMGEN, "--no-mirror", "-q", "-f", "psd", "-c", "32", *extra,
                                    str(hdr)]))
    best = {k: min(v) for k, v in runs.items()}
    st = min(stages, key=lambda s: s["total"])
    cm_total = best["ld"][0] + best["irr"][0] + best["sh"][0]
    cpu = {k: min(r[2] for r in v) for k, v in runs.items()}
    print(f"probegrid filter --size 128: {best['pg'][0]:.2f} s wall, {cpu['pg']:.2f} s CPU, "
          f"{best['pg'][1]:.0f} MB peak (best of {args.repeat}); stages of that run: "
          + ", ".join(f"{k} {v:.3f}" for k, v in st.items() if k != "total")
          + f"; start-up and imports {best['pg'][0] - st['total']:.2f} s"
          + (" (bytecode compiled every run: --no-bytecode)" if args.no_bytecode
             else " (bytecode cached, as installed)"))
    cm_cpu = cpu["ld"] + cpu["irr"] + cpu["sh"]
    print(f"cmgen: ld {best['ld'][0]:.2f} s + irradiance {best['irr'][0]:.2f} s + sh "
          f"{best['sh'][0]:.2f} s = {cm_total:.2f} s wall, {cm_cpu:.2f} s CPU "
          f"({max(best['ld'][1], best['irr'][1]):.0f} MB peak)")
    ratio = best["pg"][0] / cm_total
    print(f"ratio probegrid / cmgen = {ratio:.2f} wall, {cpu['pg'] / cm_cpu:.2f} CPU (target "
          f"<= 0.5 wall: {'MET' if ratio <= 0.5 else 'NOT MET'}); load average now "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")

    # ---------------- errors ----------------
    cube = to_cube(img, "equirect", 128)          # what the command filters
    key = hashlib.sha1(img.tobytes()).hexdigest()
    diff_ref = cached(cache, f"diffuse512 {key}",
                      lambda: diffuse_exact(to_cube(img, "equirect", 512), 32))
    # what the command computes for a 128^2 cube: one pass of dense sums for the diffuse map
    # and every GGX level (probegrid.filter)
    ours_d, *chain_rest = symmetric_zonal_sums(
        cube, [ZonalOutput(32, "cosine")] + [ZonalOutput(128 >> k, "ggx", (k / 7) ** 2)
                                            for k in range(1, 8)], workers=2)
    chain = [cube, *chain_rest]
    cm_levels = sorted(int(m.group(1)) for p in (work / "ld" / hdr.stem).glob("m*_px.psd")
                       if (m := re.match(r"m(\d+)_px", p.stem)))
    theirs0 = np.stack([read_rgb(work / "ld" / hdr.stem / f"m0_{f}.psd") for f in FACES])
    perm = symmetry_permutations(128)
    sym = int(np.argmin([np.abs(theirs0.reshape(-1, 3) - cube.reshape(-1, 3)[perm[k]]).mean()
                         for k in range(48)]))
    cm_d = to_ours(np.stack([read_rgb(work / "irr" / hdr.stem / f"i_{f}.psd") for f in FACES]),
                   sym)
    scale = float(np.median(cm_d / diff_ref))
    e_o, e_c = errors(ours_d, diff_ref), errors(cm_d, diff_ref)
    print(f"diffuse 32^2 vs converged (512^2 exact sum): probegrid rms {e_o[0]:.2e} max "
          f"{e_o[1]:.2e} (mean {np.mean(np.abs(ours_d - diff_ref) / diff_ref):.3%}); cmgen rms "
          f"{e_c[0]:.2e} max {e_c[1]:.2e} (its median ratio to the reference {scale:.3f})")

    # GGX
    levels = len(chain)
    cube256 = cached(cache, f"cube256 {key}", lambda: to_cube(img, "equirect", 256))
    rng = np.random.default_rng(0)
    text = subprocess.run([CMGEN, "--no-mirror", "-s", "128", "-f", "psd", "-c", "32",
                           f"--ibl-ld={work / 'ld2'}", str(hdr)], capture_output=True, text=True,
                          check=True).stdout  # it prints each level's roughness
    cm_r = {int(k): float(r) for k, r in
            re.findall(r"Level (\d+), roughness = \S+, roughness \(perceptual\) = (\S+)", text)}
    print(f"GGX at up to {args.texels} random texels per level; errors vs the 256^2 dense sum "
          "(rms / max relative); floor = the dense sum over probegrid's own 128^2 cube")
    print(f"{'lvl':>3} {'size':>4} {'r':>6} | {'floor':>17} | {'probegrid':>17} {'x floor':>8} | "
          f"{'cmgen r':>7} {'cmgen':>17} {'floor at its r':>17}")
    worst = worst_all = 0.0
    for k in range(1, levels):
        s = 128 >> k
        dirs_all = texel_directions(s).reshape(-1, 3)
        pick = (np.arange(len(dirs_all)) if len(dirs_all) <= 1.5 * args.texels
                else np.sort(rng.choice(len(dirs_all), args.texels, replace=False)))
        dirs = dirs_all[pick]
        r = k / (levels - 1)
        ref = cached(cache, f"ggx256 {key} {r} {s} {args.texels}",
                     lambda dirs=dirs, r=r: dense_ggx_at(cube256, dirs, r * r))
        floor = errors(dense_ggx_at(cube, dirs, r * r), ref)
        ours = errors(chain[k].reshape(-1, 3)[pick], ref)
        x = max(ours[0] / floor[0], ours[1] / floor[1])
        worst = max(worst, x) if 0.17 <= r <= 0.43 else worst
        worst_all = max(worst_all, x)
        line = (f"{k:>3} {s:>4} {r:6.3f} | {floor[0]:8.2e} {floor[1]:8.2e} | {ours[0]:8.2e} "
                f"{ours[1]:8.2e} {x:8.2f} |")
        if k in cm_levels and k in cm_r:
            theirs = to_ours(np.stack([read_rgb(work / "ld" / hdr.stem / f"m{k}_{f}.psd")
                                       for f in FACES]), sym)
            rc = cm_r[k]
            ref_c = cached(cache, f"ggx256 {key} {rc} {s} {args.texels}",
                           lambda dirs=dirs, rc=rc: dense_ggx_at(cube256, dirs, rc * rc))
            ec = errors(theirs.reshape(-1, 3)[pick], ref_c)
            fc = errors(dense_ggx_at(cube, dirs, rc * rc), ref_c)
            line += f" {rc:7.3f} {ec[0]:8.2e} {ec[1]:8.2e} {fc[0]:8.2e} {fc[1]:8.2e}"
        print(line)
    print(f"mid roughness (0.17-0.42): worst probegrid / floor = {worst:.2f}; every level: "
          f"{worst_all:.2f} (target <= 2: {'MET' if worst_all <= 2 else 'NOT MET'})")

    # SH
    print("SH diffuse vs the converged diffuse (mean / max relative), beside the best each band "
          "count allows (exact projection of every input pixel):")
    for bands in (3, 5, 7, 9):
        d, info = diffuse_sh(cube, 32, bands=bands)
        best_d = sh.diffuse_cube(sh.project_equirect(img, bands=bands), 32, bands=bands)
        e = np.abs(d - diff_ref) / diff_ref
        eb = np.abs(best_d - diff_ref) / diff_ref
        print(f"  {bands} bands ({bands * bands:>2} coefficients): probegrid {e.mean():7.3%} / "
              f"{e.max():8.2%}   best {eb.mean():7.3%} / {eb.max():8.2%}   ratio "
              f"{e.mean() / eb.mean():.3f} / {e.max() / eb.max():.3f}"
              + ("   (irradiance < 0 somewhere)" if info.negative else ""))
    return {"ratio": ratio}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--texels", type=int, default=1024)
    ap.add_argument("--cache", type=Path,
                    default=Path(tempfile.gettempdir()) / "probegrid-bench-cli")
    ap.add_argument("--hdr", nargs="*", default=None, help="stems of files in tests/data/hdr")
    ap.add_argument("--no-bytecode", action="store_true",
                    help="keep PYTHONDONTWRITEBYTECODE if the environment sets it (every run then "
                         "compiles probegrid's modules from source, ~0.07 s CPU)")
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    files = sorted(DATA.glob("*.hdr"))
    if args.hdr:
        files = [f for f in files if any(h in f.stem for h in args.hdr)]
    with tempfile.TemporaryDirectory() as tmp:
        for f in files:
            bench(f.stem.split("_")[0], f, Path(tmp), args.cache, args)
        if files:
            bench_defaults(files[-1], Path(tmp), args)


def bench_defaults(hdr: Path, work: Path, args: argparse.Namespace) -> None:
    """A large input with every default: a 1500 x 750 lat-long (``hdr`` resampled bilinearly) with
    every default (the cube size chosen from the input: 256^2), against 5 s and 500 MB, beside
    cmgen's three runs at 256^2 on the same file."""
    img = read_rgb(hdr).astype(np.float64)
    h, w = 750, 1500
    y = (np.arange(h) + 0.5) * img.shape[0] / h - 0.5
    x = (np.arange(w) + 0.5) * img.shape[1] / w - 0.5
    y0 = np.clip(np.floor(y).astype(int), 0, img.shape[0] - 2)
    x0 = np.floor(x).astype(int)
    fy = np.clip(y - y0, 0, 1)[:, None, None]
    fx = (x - x0)[None, :, None]
    x0 %= img.shape[1]
    x1 = (x0 + 1) % img.shape[1]  # (the longitude wraps)
    big = ((1 - fy) * ((1 - fx) * img[y0][:, x0] + fx * img[y0][:, x1])
           + fy * ((1 - fx) * img[y0 + 1][:, x0] + fx * img[y0 + 1][:, x1]))
    src = work / "big_1500x750.hdr"
    out = oiio.ImageOutput.create(str(src))
    out.open(str(src), oiio.ImageSpec(w, h, 3, oiio.FLOAT))
    out.write_image(big.astype(np.float32))
    out.close()
    print(f"\n===== defaults: {hdr.name} resampled to {w}x{h} =====")
    env = None if args.no_bytecode else {k: v for k, v in os.environ.items()
                                         if k != "PYTHONDONTWRITEBYTECODE"}
    res = work / "big"
    runs, cm = [], []
    for _ in range(args.repeat):
        shutil.rmtree(res, ignore_errors=True)
        runs.append(timed([PROBEGRID, "filter", str(src), "--out", str(res)], env))
        cm.append(sum(timed([CMGEN, "--no-mirror", "-q", "-f", "psd", "-c", "32", *extra,
                             str(src)])[0]
                      for extra in (["-s", "256", f"--ibl-ld={work / 'ld'}"],
                                    ["-s", "32", f"--ibl-irradiance={work / 'irr'}"],
                                    ["--sh=3", f"--sh-output={work / 'sh.txt'}"])))
    manifest = json.loads((res / "manifest.json").read_text())
    wall, rss = min(r[0] for r in runs), max(r[1] for r in runs)
    ok = "MET" if wall <= 5.0 and rss <= 500 else "NOT MET"
    decoded = w * h * 3 * 4 / 2**20  # the input as the filter holds it: float32 RGB
    print(f"probegrid filter (all defaults: {manifest['input']['cube_size']}^2 cube, "
          f"{manifest['specular']['levels']} GGX levels): {wall:.2f} s wall (best of "
          f"{args.repeat}), {min(r[2] for r in runs):.2f} s CPU, {rss:.0f} MB peak (largest; "
          f"{rss / decoded:.0f} x the decoded input's {decoded:.1f} MB); "
          f"target <= 5 s and <= 500 MB: {ok}; cmgen's three runs at 256^2: {min(cm):.2f} s")


if __name__ == "__main__":
    main()
