"""Memory-mapping benchmark: the peak mapping count and the compiles of a study's training and evaluation.

    python -m experiments.bench_mappings [--data PATH] [--factor F] [--preset tiny] [--methods 2dgs,patexgs]
                                         [--out DIR] [--test-views N] [--no-lpips] [--json out.json]

Runs the paper's protocol (:mod:`experiments.mipnerf360`, in this process, output in ``--out``,
default a temporary folder) and measures what limits a long run: XLA keeps each compiled program's
machine code in memory mappings of its own, and Linux caps a process's mappings
(``vm.max_map_count``, 65,530 by default; see :mod:`patexgs_jax.memory_maps`). A thread samples
``/proc/self/maps`` every ``--interval`` seconds, and the count is also read after every training
step and every evaluated view; compiles are counted from JAX's backend-compile events (persistent
cache hits included: a loaded program holds mappings too), by function, and the traces of the
training step and of the renderer. Printed per phase (each method's training, each method's
evaluation): peak mappings, mappings at the end, compiles, step traces, renderer traces; then the
overall peak against the default cap of 65,530. ``--json`` writes the same figures and the
per-step / per-view samples.
"""

from __future__ import annotations

import argparse
import collections
import importlib
import platform
import sys
import tempfile
import threading
import time

DEFAULT_LIMIT = 65_530
SCHEMA = 1
MAX_SAMPLES = 400  # samples kept in the JSON file (evenly thinned; the peak is computed from all)


class Meter:
    """Mapping samples and compile counts, attributed to the current phase."""

    def __init__(self, interval: float, max_seconds: float | None = None):
        from patexgs_jax import memory_maps

        self.memory_maps = memory_maps
        self.interval = interval
        self.max_seconds = max_seconds
        self.interrupted = False
        self.phase = "setup"
        self.phases: dict = collections.OrderedDict()
        self.samples: list = []  # (seconds, phase, event, maps, compiles)
        self.compiles = collections.Counter()
        self.t0 = time.perf_counter()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample_loop, daemon=True)
        self._enter(self.phase)

    # -- counting ---------------------------------------------------------------------------------
    def _enter(self, phase: str) -> None:
        from patexgs_jax.render import TRACE_COUNTS
        from patexgs_jax.training.step import STEP_TRACES
        self.phase = phase
        maps = self.maps()
        self.phases.setdefault(phase, dict(peak=maps, start=maps, end=maps, compiles=0, step_traces=0,
                                           render_traces=0, seconds=0.0, by_function=collections.Counter()))
        self._marks = (sum(STEP_TRACES.values()), sum(TRACE_COUNTS.values()), time.perf_counter())

    def _leave(self) -> None:
        from patexgs_jax.render import TRACE_COUNTS
        from patexgs_jax.training.step import STEP_TRACES
        p = self.phases[self.phase]
        p["end"] = self.maps()
        p["peak"] = max(p["peak"], p["end"])
        p["step_traces"] += sum(STEP_TRACES.values()) - self._marks[0]
        p["render_traces"] += sum(TRACE_COUNTS.values()) - self._marks[1]
        p["seconds"] += time.perf_counter() - self._marks[2]

    def set_phase(self, phase: str) -> None:
        self._leave()
        self._enter(phase)

    def maps(self) -> int:
        m = self.memory_maps.memory_maps()
        return 0 if m is None else m[0]

    def record(self, event: str) -> None:
        n = self.maps()
        p = self.phases[self.phase]
        p["peak"] = max(p["peak"], n)
        self.samples.append((round(time.perf_counter() - self.t0, 3), self.phase, event, n,
                             sum(self.compiles.values())))

    def on_compile(self, event: str, duration: float, **kw) -> None:
        if event != "/jax/core/compile/backend_compile_duration":
            return
        name = kw.get("fun_name", "?")
        self.compiles[name] += 1
        p = self.phases[self.phase]
        p["compiles"] += 1
        p["by_function"][name] += 1

    def _sample_loop(self) -> None:
        import _thread

        while not self._stop.wait(self.interval):
            n = self.maps()
            p = self.phases.get(self.phase)
            if p is not None:
                p["peak"] = max(p["peak"], n)
            if self.max_seconds is not None and time.perf_counter() - self.t0 > self.max_seconds:
                self.interrupted = True
                _thread.interrupt_main()  # the study stops with KeyboardInterrupt; figures so far are kept
                return

    def start(self) -> None:
        import jax

        jax.monitoring.register_event_duration_secs_listener(self.on_compile)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        self._leave()


def instrument(meter: Meter) -> None:
    """Hooks the study's training runs, training steps, evaluations and evaluated views."""
    from patexgs_jax import training
    from patexgs_jax.training.trainer import Trainer

    M = importlib.import_module("experiments.mipnerf360")
    E = importlib.import_module("patexgs_jax.evaluation")

    orig_after = Trainer.after_step

    def after_step(self, step):
        orig_after(self, step)
        meter.record(f"step {step}")

    Trainer.after_step = after_step

    orig_train = training.train  # (the study imports it from patexgs_jax.training when it runs)

    def train(ds, cfg, *args, **kw):
        meter.set_phase(f"train {cfg.method}")
        try:
            return orig_train(ds, cfg, *args, **kw)
        finally:
            meter.set_phase("setup")

    training.train = train

    orig_eval = M.Study.evaluate

    def evaluate(self, scene, key, result, ds, cfg):
        meter.set_phase(f"evaluate {key}")
        try:
            return orig_eval(self, scene, key, result, ds, cfg)
        finally:
            meter.set_phase("setup")

    M.Study.evaluate = evaluate

    view = getattr(E, "_evaluate_view", None)
    if view is not None:  # (older code evaluates in one function: the sampler thread still sees it)
        def evaluate_view(renderer, i, v, *args, **kw):
            view(renderer, i, v, *args, **kw)
            meter.record(f"view {i}")

        E._evaluate_view = evaluate_view


def report(meter: Meter, limit: int | None) -> dict:
    phases = {}
    for name, p in meter.phases.items():
        if name == "setup" and p["compiles"] == 0:
            continue
        phases[name] = {k: (dict(v.most_common()) if k == "by_function" else v) for k, v in p.items()}
    peak = max([p["peak"] for p in meter.phases.values()] + [s[3] for s in meter.samples] + [0])
    return dict(peak_maps=peak, default_limit=DEFAULT_LIMIT, peak_share_of_default=peak / DEFAULT_LIMIT,
                kernel_limit=limit, compiles=sum(meter.compiles.values()),
                compiles_by_function=dict(meter.compiles.most_common()), phases=phases,
                samples=meter.samples)


def print_report(rep: dict) -> None:
    print("\n| phase | seconds | peak maps | maps at end | compiles | step traces | renderer traces | most compiled |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |")
    for name, p in rep["phases"].items():
        top = ", ".join(f"{k} {v}" for k, v in list(p["by_function"].items())[:3])
        print(f"| {name} | {p['seconds']:.0f} | {p['peak']:,} | {p['end']:,} | {p['compiles']} | {p['step_traces']} | "
              f"{p['render_traces']} | {top} |")
    last = rep["samples"][-1] if rep["samples"] else None
    if last is not None:
        print(f"\nlast sample: {last[2]} of {last[1]} at {last[0]:.0f} s: {last[3]:,} mappings, {last[4]} compiles")
    print(f"\npeak {rep['peak_maps']:,} mappings = {100 * rep['peak_share_of_default']:.1f}% of the default cap "
          f"{DEFAULT_LIMIT:,} (this kernel's: {rep['kernel_limit']}); {rep['compiles']} compiles in all")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.bench_mappings", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None, help="one scene (default: the embedded synthetic scene)")
    ap.add_argument("--factor", type=int, default=None, help="image downsampling of --data (default: as train's)")
    ap.add_argument("--preset", default="tiny", choices=["tiny", "small", "paper"],
                    help="the study's schedule (default tiny)")
    ap.add_argument("--methods", default="2dgs,patexgs",
                    help="the study's methods, comma-separated (default 2dgs,patexgs)")
    ap.add_argument("--iters-2dgs", type=int, default=None, help="steps of the 2DGS stage (default: the preset's)")
    ap.add_argument("--iters-tex", type=int, default=None, help="steps of the texture stage (default: the preset's)")
    ap.add_argument("--test-views", type=int, default=None, help="at most this many test views evaluated")
    ap.add_argument("--out", default=None, help="the study's output folder (default: a temporary one)")
    ap.add_argument("--no-lpips", action="store_true", help="skip LPIPS in the evaluation")
    ap.add_argument("--no-compile-cache", action="store_true", help="compile everything (no persistent XLA cache)")
    ap.add_argument("--interval", type=float, default=0.2, help="seconds between samples of the mapping count")
    ap.add_argument("--max-seconds", type=float, default=None,
                    help="stop the study after this long and report the figures so far")
    ap.add_argument("--json", default=None, help="also write the figures here (with the commit and machine)")
    args = ap.parse_args(argv)

    M = importlib.import_module("experiments.mipnerf360")
    meter = Meter(args.interval, args.max_seconds)
    if not args.no_compile_cache:
        meter.memory_maps.enable_compile_cache()
    instrument(meter)
    maps = meter.memory_maps.memory_maps()
    limit = None if maps is None else maps[1]
    out = args.out or tempfile.mkdtemp(prefix="bench_mappings_")
    config = {k: v for k, v in dict(preset=args.preset, factor=args.factor, iters_2dgs=args.iters_2dgs,
                                    iters_tex=args.iters_tex, test_views=args.test_views).items() if v is not None}
    meter.start()
    t = time.perf_counter()
    try:
        M.run(args.data, methods=[m.strip() for m in args.methods.split(",") if m.strip()], out=out,
              renders=0, use_lpips=not args.no_lpips, **config)
    except KeyboardInterrupt:
        if not meter.interrupted:
            raise
        print(f"stopped after --max-seconds {args.max_seconds:g}", flush=True)
    finally:
        meter.stop()
    rep = report(meter, limit)
    rep.update(seconds=time.perf_counter() - t, data=args.data, factor=args.factor, preset=args.preset,
               methods=args.methods, machine=platform.platform(), out=out, interrupted=meter.interrupted)
    print_report(rep)
    if args.json:
        from experiments import provenance

        samples = rep.pop("samples")
        step = max(1, -(-len(samples) // MAX_SAMPLES))
        phases = rep.pop("phases")
        rep.pop("machine")  # the provenance header says it
        provenance.write_benchmark_json(args.json, [dict(phase=k, **v) for k, v in phases.items()], SCHEMA,
                                        **rep, samples=samples[::step])
        print(f"written to {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
