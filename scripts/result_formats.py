#!/usr/bin/env python
"""Which array file for a run's results: write time, size and load time of a formation
result's arrays at n agents, in each candidate format, against the ``result.json`` of before
(positions as nested JSON lists).

    python scripts/result_formats.py --agents 10000 100000 --repeat 3 --output runs/formats

The data: the paper's point-mass geometry with n agents and N = 10 intervals (straight lines
from the start line to the circle at the initial angles, rest-to-rest profile 3t² − 2t³):
positions (n, 11, 2), interval velocities and controls (n, 10, 2), per-agent cost, mass,
solver status code, iterations, constraint violation; φ (n,). Formats: ``json`` (today's
layout: json.dumps of the nested lists + write; json.load + np.asarray), netCDF4 through
xarray with the ``h5netcdf`` and the ``netcdf4`` engines, uncompressed and with zlib level 1
(shuffle on), and zarr v3 (a directory store and a zip store, zarr's default compressor).
Write = build the Dataset + write the file; load = open + load every array into memory. Each
timed ``--repeat`` times (median). Writes ``result_formats.json`` and ``result_formats.png``.
"""

from __future__ import annotations

import argparse
import gc
import json
import shutil
import statistics
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import xarray as xr

from ocpar.examples import formation_point_masses
from ocpar.plotting import pyplot, save

INTERVALS = 10


def formation_arrays(n: int) -> dict[str, np.ndarray]:
    """A formation result's arrays at ``n`` agents (module docstring)."""
    problem = formation_point_masses.make(agents=n)
    phi = problem.initial_phi()
    end = problem.final_positions(phi)
    t = np.linspace(0, 1, INTERVALS + 1)
    profile = 3 * t**2 - 2 * t**3
    q = problem.starts[:, None, :] + profile[None, :, None] * (end - problem.starts)[:, None]
    h = 1.0 / INTERVALS
    v = np.diff(q, axis=1) / h
    u = np.diff(v, axis=1, prepend=0.0) / h
    rng = np.random.default_rng(0)
    return {"position": q, "velocity": v, "control": u, "phi": phi,
            "cost": np.einsum("ikj,ikj->i", u, u) * h, "mass": np.ones(n),
            "status": np.zeros(n, np.int8), "iterations": rng.integers(1, 4, n).astype(np.int32),
            "violation": rng.uniform(0, 1e-12, n)}


def dataset(arrays: dict[str, np.ndarray]) -> xr.Dataset:
    dims = {"position": ("agent", "node", "q"), "velocity": ("agent", "interval", "q"),
            "control": ("agent", "interval", "u")}
    return xr.Dataset({name: (dims.get(name, ("agent",)), value)
                       for name, value in arrays.items()})


def write_json(arrays: dict[str, np.ndarray], path: Path) -> None:
    """Today's layout: the positions as nested lists beside the per-agent lists."""
    data = {"trajectories": arrays["position"].tolist(), "phi": arrays["phi"].tolist(),
            "agent_costs": arrays["cost"].tolist()}
    gc.disable()   # as RunResult.write_json did: no collections while the lists are built
    try:
        text = json.dumps(data)
    finally:
        gc.enable()
    path.write_text(text)


def load_json(path: Path) -> None:
    with path.open() as f:
        data = json.load(f)
    np.asarray(data["trajectories"])


def netcdf_writer(engine: str, compress: bool) -> Callable[[dict, Path], None]:
    def write(arrays: dict[str, np.ndarray], path: Path) -> None:
        ds = dataset(arrays)
        encoding = ({name: {"zlib": True, "complevel": 1, "shuffle": True} for name in ds}
                    if compress else None)
        ds.to_netcdf(path, engine=engine, encoding=encoding)
    return write


def netcdf_loader(engine: str) -> Callable[[Path], None]:
    def load(path: Path) -> None:
        with xr.open_dataset(path, engine=engine) as ds:
            ds.load()
    return load


def write_zarr(arrays: dict[str, np.ndarray], path: Path) -> None:
    dataset(arrays).to_zarr(path, mode="w", zarr_format=3, consolidated=True)


def load_zarr(path: Path) -> None:
    with xr.open_zarr(path, zarr_format=3) as ds:
        ds.load()


def write_zarr_zip(arrays: dict[str, np.ndarray], path: Path) -> None:
    import zarr.storage
    with warnings.catch_warnings(), zarr.storage.ZipStore(path, mode="w") as store:
        warnings.simplefilter("ignore")   # zarr: "consolidated metadata", zip "duplicate name"
        dataset(arrays).to_zarr(store, zarr_format=3, consolidated=False)


def load_zarr_zip(path: Path) -> None:
    import zarr.storage
    with zarr.storage.ZipStore(path, mode="r") as store, \
            xr.open_zarr(store, zarr_format=3, consolidated=False) as ds:
        ds.load()


#: name: (file name, writer, loader)
FORMATS = {
    "json": ("result.json", write_json, load_json),
    "h5netcdf": ("result.nc", netcdf_writer("h5netcdf", False), netcdf_loader("h5netcdf")),
    "h5netcdf zlib1": ("result.nc", netcdf_writer("h5netcdf", True),
                       netcdf_loader("h5netcdf")),
    "netcdf4": ("result.nc", netcdf_writer("netcdf4", False), netcdf_loader("netcdf4")),
    "netcdf4 zlib1": ("result.nc", netcdf_writer("netcdf4", True), netcdf_loader("netcdf4")),
    "zarr v3 dir": ("result.zarr", write_zarr, load_zarr),
    "zarr v3 zip": ("result.zarr.zip", write_zarr_zip, load_zarr_zip),
}


def size_of(path: Path) -> int:
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return path.stat().st_size


def remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()


def measure(arrays: dict[str, np.ndarray], where: Path, repeat: int) -> dict[str, dict]:
    """Per format the median write and load times (s) and the size (bytes); the formats
    alternate within each repetition."""
    times: dict[str, dict[str, list[float]]] = {f: {"write": [], "load": []} for f in FORMATS}
    sizes = {}
    for _ in range(repeat):
        for name, (file, write, load) in FORMATS.items():
            path = where / file
            remove(path)
            start = time.perf_counter()
            write(arrays, path)
            times[name]["write"].append(time.perf_counter() - start)
            sizes[name] = size_of(path)
            start = time.perf_counter()
            load(path)
            times[name]["load"].append(time.perf_counter() - start)
            remove(path)
    return {name: {"write_s": statistics.median(t["write"]),
                   "load_s": statistics.median(t["load"]), "size_bytes": sizes[name]}
            for name, t in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--repeat", type=int, default=3, help="timed runs per format (median)")
    parser.add_argument("--output", type=Path, default=Path("runs/result-formats"))
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    scratch = args.output / "scratch"
    scratch.mkdir(exist_ok=True)
    report = {"intervals": INTERVALS, "repeat": args.repeat, "agents": {}}
    for n in args.agents:
        rows = measure(formation_arrays(n), scratch, args.repeat)
        report["agents"][str(n)] = rows
        for name, row in rows.items():
            print(f"n {n:>8}  {name:<15} write {row['write_s']:7.3f} s  load "
                  f"{row['load_s']:7.3f} s  size {row['size_bytes'] / 1e6:8.2f} MB", flush=True)
    shutil.rmtree(scratch)
    (args.output / "result_formats.json").write_text(json.dumps(report, indent=2))

    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    names = list(FORMATS)
    width = 0.8 / len(args.agents)
    for k, n in enumerate(args.agents):
        rows = report["agents"][str(n)]
        x = np.arange(len(names)) + k * width
        for ax, key, scale in zip(axes, ("write_s", "load_s", "size_bytes"), (1, 1, 1e-6),
                                  strict=True):
            ax.bar(x, [rows[f][key] * scale for f in names], width, label=f"{n:,} agents")
    for ax, label in zip(axes, ("write (s)", "load (s)", "size (MB)"), strict=True):
        ax.set_xticks(np.arange(len(names)) + width * (len(args.agents) - 1) / 2, names,
                      rotation=35, ha="right")
        ax.set_ylabel(label)
        ax.set_yscale("log")
        ax.legend()
    fig.suptitle("formation result arrays: write, load, size per format (median of "
                 f"{args.repeat})")
    save(fig, args.output / "result_formats.png")
    print(f"wrote {args.output / 'result_formats.json'}, {args.output / 'result_formats.png'}")


if __name__ == "__main__":
    main()
