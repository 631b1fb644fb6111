"""Command-line subcommands ``tawarp design``, ``tawarp rank``, ``tawarp sweep``.

Each registers its subcommand with ``--device``, ``--quiet``, ``-o``; figures go beside
the JSON output.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..io import CLAIM_HELP, GENERATOR, claim_outputs
from .common import _common, _say, check_network_options, check_onset_search, check_option, check_seed, parse_list

VAR_HELP = (
    "design variable, repeatable: NAME=LOW:HIGH[:log] (NAME: heat_input or Q, SEGMENT.FIELD such as "
    "stack.length, stack.porosity, stack.pore_radius, hot_hx.length, or stack.position), "
    "material=NAME,NAME,... (catalogue materials in the stack), NAME=VALUE (fixed); sweeps: "
    "NAME=LOW:HIGH:COUNT[:log] or NAME=v1,v2,... (a grid axis of COUNT points)"
)


def _floats(text: str) -> np.ndarray:
    return parse_list(text)


def _objectives(text: str) -> list[str]:
    """The ``--objectives`` comma list; an unknown name is refused naming the option."""
    from ..design.objectives import OBJECTIVES

    names = [o.strip() for o in text.split(",") if o.strip()]
    check_option(bool(names), "--objectives", repr(text), f"give one or more of {', '.join(OBJECTIVES)}")
    for o in names:
        check_option(
            o in OBJECTIVES, "--objectives", text, f"unknown objective {o!r}; choose from {', '.join(OBJECTIVES)}"
        )
    return names


def _check_T_limit(args) -> None:
    check_option(
        getattr(args, "no_T_limit", False) or (np.isfinite(args.T_limit) and args.T_limit > 0),
        "--T-limit",
        args.T_limit,
        "expected a temperature limit > 0 K",
    )


def _space(args, grid: bool = False):
    from ..design.catalogue import load_catalogue
    from ..model.core import load_core
    from ..design.space import DesignSpace, parse_variable

    core = load_core(args.core)
    cat = load_catalogue(args.catalogue or [])
    variables = [parse_variable(v, grid=grid) for v in (args.var or [])]
    if not variables:
        raise ValueError("give at least one --var")
    fixed = [v for v in variables if not v.categorical and v.low == v.high and len(v.values) <= 1]
    q = args.heat_input
    changes = {}
    for v in fixed:
        if v.name == "heat_input":
            q = v.low
        else:
            changes[v.name] = v.low
    variables = [v for v in variables if v not in fixed]
    if changes:
        core = core.replace(**changes)
    return DesignSpace(core, variables, catalogue=cat, segment=args.segment, heat_input=q)


def _settings(args):
    from ..model.forward import ForwardSettings

    return ForwardSettings(device=args.device)


def _add_space_args(p, network: bool = False):
    """The design space's arguments; ``network``: the command also takes a network engine."""
    from ..model.core import paper_cores

    p.add_argument(
        "core",
        help=f"core TOML file, or a bundled core: {', '.join(paper_cores())}"
        + ("; or a network engine file (traveling_wave): the lowest onset T_hot / T_cold" if network else ""),
    )
    p.add_argument("--var", action="append", help=VAR_HELP)
    p.add_argument(
        "--heat-input",
        "--Q",
        dest="heat_input",
        type=float,
        default=9.0,
        help="heat input [W] when it is not a --var (default: %(default)s)",
    )
    p.add_argument("--catalogue", action="append", help="extra materials: a TOML catalogue or a fit.json (repeatable)")
    p.add_argument("--segment", default="stack", help="the segment the design is about (default: %(default)s)")


# -- design ------------------------------------------------------------------------------
def _uncertain_material(text: str | None, catalogue):
    """A catalogue material by name, or the material of a ``tawarp fit`` result (fit.json)."""
    from ..design.catalogue import Material

    if text is None:
        return None
    if text in catalogue:
        return catalogue[text]
    if not Path(text).exists():
        raise KeyError(f"--uncertainty {text!r}: neither a catalogue material ({', '.join(catalogue)}) nor a file")
    return Material.from_fit_json(text)


def _onset_spec(args):
    from ..design.catalogue import load_catalogue
    from ..design.objectives import OnsetSpec

    return OnsetSpec(
        engine=args.onset_engine,
        Q_max=args.Q_max,
        n_bracket=args.bracket,
        uncertainty=_uncertain_material(args.uncertainty, load_catalogue(args.catalogue or [])),
        n_draws=args.draws,
        seed=args.seed,
        segment=args.segment,
    )


def _add_T_limit(p, what: str) -> None:
    """``--T-limit`` [K], ``what`` it limits, default :data:`DEFAULT_T_LIMIT`."""
    from ..design.objectives import DEFAULT_T_LIMIT

    p.add_argument(
        "--T-limit", dest="T_limit", type=float, default=DEFAULT_T_LIMIT, help=what + " (default: %(default)s)"
    )


def _add_onset_args(p):
    p.add_argument(
        "--onset-engine",
        default="standing_wave",
        help="onset objectives: the engine (TOML or bundled name) whose resonator closes the core "
        "(default: %(default)s)",
    )
    p.add_argument(
        "--Q-max",
        dest="Q_max",
        type=float,
        default=200.0,
        help="onset: largest heat input searched [W]; no onset below it counts as inf (default: %(default)s)",
    )
    p.add_argument(
        "--bracket",
        type=int,
        default=9,
        help="onset: heat inputs on [0, Q-max] bracketing the onset (default: %(default)s)",
    )
    p.add_argument(
        "--uncertainty",
        default=None,
        help="Q_onset_p90: the stack material's uncertainty, a catalogue name or a fit.json",
    )
    p.add_argument(
        "--draws",
        type=int,
        default=64,
        help="Q_onset_p90: parameter sets drawn per design (default: %(default)s)",
    )


def _is_network(path: str) -> bool:
    """``path`` names a network engine file (``[[branch]]`` tables), bundled or not."""
    from ..model.core import bundled, read_toml
    from ..model.network import is_network_file

    if not Path(path).exists() and path not in bundled("engines"):
        return False
    return is_network_file(read_toml(path, "engines")[1])


def _design_network(args) -> int:
    """``tawarp design NETWORK.toml --var SEGMENT.FIELD=LOW:HIGH[:log] ...``: the lowest onset
    T_hot / T_cold (:func:`tawarp.design.network_design.search_network`)."""
    from ..design.network_design import search_network
    from ..design.space import parse_variable
    from ..io import write_json
    from ..model.network import load_network

    net = load_network(args.core)
    variables = [parse_variable(v) for v in (args.var or [])]
    if not variables:
        raise ValueError("give at least one --var SEGMENT.FIELD=LOW:HIGH[:log]")
    check_network_options(args)
    out = Path(args.output)
    claim_outputs(out / "design.json", why="the design report")
    out.mkdir(parents=True, exist_ok=True)
    has_segment = any(s.name == args.segment for br in net.branches for s in br.segments)
    report = search_network(
        net,
        variables,
        n_trials=args.trials,
        batch=args.batch,
        seed=args.seed,
        T_max=args.T_ratio_max * net.gas.T_cold,
        device=args.device,
        segment=args.segment if has_segment else None,
        amplitude=args.amplitude,
        keep=args.keep,
    )
    report["generator"] = f"{GENERATOR} design"
    write_json(out / "design.json", report)
    if report["best"]:
        b = report["best"][0]
        _say(args, f"best: T_hot/T_cold = {b['T_ratio']:.6g}, f = {b['f_onset_Hz']:.6g} Hz at {b['params']}")
    _say(
        args,
        f"{report['evaluated']} designs, {report['designs_per_minute']:.3g}/min; "
        f"the file's design: T_hot/T_cold = {report['file_design']['T_ratio']:.6g}; wrote {out / 'design.json'}",
    )
    return 0


def cmd_design(args) -> int:
    from ..io import write_json
    from ..design.samplers import check_batch
    from ..design.search import objective_definitions, search
    from ..design.storage import study_summary
    from ..design.plots import plot_best_profiles, plot_history, plot_pareto

    # every check before the output folder is made: a refused command leaves nothing behind
    check_option(args.trials >= 1, "--trials", args.trials, "expected a number of trials >= 1")
    check_option(args.batch >= 1, "--batch", args.batch, "expected a population of at least 1 trial")
    check_option(args.keep >= 1, "--keep", args.keep, "expected a number of best designs >= 1")
    check_option(args.draws >= 1, "--draws", args.draws, "expected a number of parameter sets >= 1")
    check_onset_search(args)
    check_seed(args)
    if _is_network(args.core):
        return _design_network(args)
    space = _space(args)
    objectives = _objectives(args.objectives)
    if args.engine == "batched":
        check_batch(
            args.batch, len(space.material.choices) if space.material is not None else 0, len(objectives), "--batch"
        )
    _check_T_limit(args)
    onset = _onset_spec(args)
    out = Path(args.output)
    claim_outputs(
        out / "design.json",
        *([] if args.no_plots else [out / "history.png", out / "pareto.png", out / "best_profiles.png"]),
        why="the design report",
    )
    out.mkdir(parents=True, exist_ok=True)
    storage = args.storage or str(out / "study.journal")
    T_limit = None if args.no_T_limit else args.T_limit
    res = search(
        space,
        objectives,
        n_trials=args.trials,
        batch=args.batch,
        storage=storage,
        study_name=args.study,
        worker=args.worker,
        seed=args.seed,
        T_limit=T_limit,
        engine=args.engine,
        settings=_settings(args),
        freqs=args.freqs,
        progress=not args.quiet,
        onset=onset,
        store=args.trial_store,
        commit_seconds=args.commit_seconds,
    )
    summary = study_summary(res.study)
    report = {
        "generator": f"{GENERATOR} design",
        "core": str(space.core.source),
        "variables": space.describe(),
        "objectives": objectives,
        "objective_definitions": objective_definitions(objectives),
        "T_limit_K": T_limit,
        "storage": storage,
        "trial_store": summary["store"],
        "study": args.study,
        "worker": args.worker,
        "engine": args.engine,
        "batch": args.batch,
        "resumed_trials": res.resumed,
        "summary": summary,
        "timing": res.timing,
        "best": res.best[: args.keep],
    }
    write_json(out / "design.json", report)
    if not args.no_plots:
        plot_history(res.study, objectives, out / "history.png", T_limit)
        if len(objectives) > 1:
            plot_pareto(res.study, objectives, res.best, out / "pareto.png")
        shown = _profile_designs(res.study, objectives, res.best, space, T_limit)
        if shown:
            plot_best_profiles(space, shown, out / "best_profiles.png", device=args.device)
    if res.best:
        b = res.best[0]
        _say(args, f"best: {b['values']} at {b['params']}")
    _say(
        args,
        f"{res.timing['evaluations']} evaluations, {res.timing['evaluations_per_minute']:.3g}/min; "
        f"wrote {out / 'design.json'}",
    )
    if summary["store"]:
        _say(
            args,
            f"all {summary['trials']} trials in the trial store {summary['store']}; the study in {storage} "
            f"holds {summary['in_study']} (the best); read all with "
            f"tawarp.design.storage.trials_table(optuna.load_study(...))",
        )
    else:
        _say(args, f"all {summary['trials']} trials in the study in {storage}")
    return 0


def _profile_designs(study, objectives, best, space, T_limit, n=5):
    """Designs whose profiles are drawn: the best of each material (one objective), or
    up to n points spread along the Pareto front."""
    from ..design.storage import best_designs

    if len(objectives) > 1:
        if len(best) <= n:
            return best
        idx = np.unique(np.linspace(0, len(best) - 1, n).round().astype(int))
        return [best[i] for i in idx]
    if space.material is None:
        return best[:1]
    return best_designs(study, objectives, T_limit, k=len(space.material.choices), per="material")


def add_design_parser(sub) -> argparse.ArgumentParser:
    from ..design.evaluate import DEFAULT_FREQS
    from ..design.objectives import OBJECTIVES

    p = _common(
        sub.add_parser(
            "design",
            help="design search (CMA-ES / NSGA-II, batched on the device, Optuna study)",
            description="Batched design search. Objectives: "
            + "; ".join(f"{o.name} [{o.unit}] ({o.direction}d): {o.long_name}" for o in OBJECTIVES.values()),
        )
    )
    _add_space_args(p, network=True)
    p.add_argument(
        "--objectives",
        default="gradient",
        help=f"comma list of {', '.join(OBJECTIVES)} (two or more: NSGA-II; default: %(default)s)",
    )
    p.add_argument("--trials", type=int, default=4096, help="trials of this worker (default: %(default)s)")
    p.add_argument("--batch", type=int, default=256, help="population = trials per launch (default: %(default)s)")
    _add_T_limit(p, "constraint T_max <= T_LIMIT [K]")
    p.add_argument("--no-T-limit", action="store_true", help="no temperature constraint")
    p.add_argument(
        "--storage",
        default=None,
        help="journal file path or database URL (sqlite:///x.db, postgresql://...); default: OUTPUT/study.journal",
    )
    p.add_argument(
        "--trial-store",
        default=None,
        help="folder of the columnar trial store that keeps every evaluated trial (HDF5, one file per "
        "worker run; the study keeps the best); default: beside a journal file "
        "(OUTPUT/study.trials/STUDY), none with a database URL (every trial in the database); "
        "with several machines give a folder they all see",
    )
    p.add_argument(
        "--commit-seconds",
        type=float,
        default=0.0,
        help="commit the evaluated generations (trial store, study, heartbeat) at most this often [s]; "
        "0: every generation (default: %(default)s); 1 keeps a GPU busy, a killed run redoing at most "
        "that much",
    )
    p.add_argument("--study", default="tawarp-design", help="study name (default: %(default)s)")
    p.add_argument("--worker", default="w0", help="this worker's name; several workers need distinct names")
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="with the worker name, seeds this worker's sampler stream (default: %(default)s)",
    )
    p.add_argument(
        "--engine",
        choices=("batched", "optuna"),
        default="batched",
        help="batched population samplers (default) or Optuna's own samplers, one ask per trial",
    )
    p.add_argument(
        "--freqs",
        type=_floats,
        default=np.array(DEFAULT_FREQS),
        help="frequencies [Hz] of acoustic_loss, list or start:stop:count",
    )
    _add_onset_args(p)
    p.add_argument(
        "--T-ratio-max",
        dest="T_ratio_max",
        type=float,
        default=4.0,
        help="a network engine file: largest T_hot/T_cold searched (default: %(default)s)",
    )
    p.add_argument(
        "--amplitude",
        type=float,
        default=1e5,
        help="a network engine file: |p| [Pa] at its first end for --segment's acoustic power (default: %(default)s)",
    )
    p.add_argument("--keep", type=int, default=20, help="best designs kept in design.json (default: %(default)s)")
    p.add_argument(
        "-o",
        "--output",
        default="tawarp-design",
        help="output folder (default: %(default)s): design.json, the study (study.journal, study.trials/ "
        "unless --storage) and figures history.png, pareto.png, best_profiles.png" + CLAIM_HELP,
    )
    p.add_argument("--no-plots", action="store_true", help="skip the figures")
    p.set_defaults(func=cmd_design)
    return p


# -- rank --------------------------------------------------------------------------------
def cmd_rank(args) -> int:
    from ..design.catalogue import load_catalogue
    from ..io import write_json
    from ..design.plots import plot_ranking
    from ..design.rank import rank_materials
    from ..model.core import load_core

    out = Path(args.output)
    if out.suffix.lower() != ".json":
        raise ValueError(
            f"-o {out}: the ranking is written as JSON and its figure beside it as .png; give a .json file name"
        )
    check_option(
        args.samples is None or args.samples >= 2, "--samples", args.samples, "expected at least 2 draws per material"
    )
    check_seed(args)
    _check_T_limit(args)
    check_onset_search(args)
    if not args.no_plots and args.by != "onset":
        claim_outputs(out.with_suffix(".png"), why="the ranking's figure")
    cat = load_catalogue(args.catalogue or [])
    mats = [m.strip() for m in args.materials.split(",")] if args.materials else None
    if mats:
        missing = [m for m in mats if m not in cat]
        if missing:
            raise KeyError(f"materials {missing} not in the catalogue ({', '.join(cat)})")
    if args.by == "onset":
        from ..model.core import read_toml
        from ..model.network import is_network_file

        if is_network_file(read_toml(args.engine, "engines")[1]):
            return _rank_network_onset(args, cat, mats, out)
    if args.samples is None:
        args.samples = 400 if args.by == "onset" else 4000
    if args.by == "onset":
        return _rank_onset(args, cat, mats, out)
    core = load_core(args.core)
    _check_segment(args.segment, core)
    res = rank_materials(
        mats,
        args.Q,
        core=core,
        segment=args.segment,
        n_samples=args.samples,
        seed=args.seed,
        T_limit=args.T_limit,
        catalogue=cat,
        settings=_settings(args),
    )
    d = res.to_dict()
    d["materials_used"] = {m: cat[m].to_dict() for m in res.materials}
    write_json(out, d)
    if not args.no_plots:
        plot_ranking(res, out.with_suffix(".png"))
    for q in res.heat_inputs:
        _say(args, f"Q = {q:g} W: " + " > ".join(res.ordering(q)))
    _say(args, f"wrote {out}")
    return 0


def _check_segment(segment: str, core) -> None:
    names = [s.name for s in core.segments]
    check_option(segment in names, "--segment", segment, f"not a segment of {core.source}; one of {', '.join(names)}")


def _rank_onset(args, cat, mats, out: Path) -> int:
    """``tawarp rank --by onset``: materials by the onset heat input of a reference engine."""
    import dataclasses

    from ..io import write_json
    from ..design.rank import rank_by_onset
    from ..model.forward import parameter_row
    from ..model.resonator import load_engine

    engine = load_engine(args.engine)
    _check_segment(args.segment, engine.core)
    changes = {}
    for t in args.set:
        name, sep, value = t.partition("=")
        if not sep:
            raise ValueError(f"--set {t!r}: expected NAME=VALUE, e.g. gas.p_mean=1e6")
        parameter_row(engine.core, name.strip())  # a KeyError listing the engine's parameters
        changes[name.strip()] = float(value)
    if changes:
        engine = dataclasses.replace(engine, core=engine.core.replace(**changes))
    res = rank_by_onset(
        mats,
        engine,
        segment=args.segment,
        n_samples=args.samples,
        seed=args.seed,
        Q_max=args.Q_max,
        n_bracket=args.bracket,
        catalogue=cat,
        settings=_settings(args),
    )
    d = res.to_dict()
    d["engine_changes"] = changes
    d["materials_used"] = {m: cat[m].to_dict() for m in res.materials}
    write_json(out, d)
    _say(args, f"{'material':<12}{'Q_onset [W]: nominal':>22}{'median':>9}{'5-95 %':>17}{'p90':>9}{'P(best)':>9}")

    def fmt(v):
        return f"{v:.3g}" if v is not None else f">{args.Q_max:g}"

    for r in res.table:
        _say(
            args,
            f"{r['material']:<12}{fmt(r['Q_onset_nominal_W']):>22}{fmt(r['Q_onset_median_W']):>9}"
            f"{fmt(r['Q_onset_p05_W']) + '-' + fmt(r['Q_onset_p95_W']):>17}{fmt(r['Q_onset_p90_W']):>9}"
            f"{r['p_best']:9.2f}",
        )
    _say(args, f"wrote {out}")
    return 0


def _rank_network_onset(args, cat, mats, out: Path) -> int:
    """``tawarp rank --by onset --engine NETWORK``: materials by the onset ratio T_hot / T_cold of
    an engine network (the NumPy reference, one design at a time)."""
    from ..io import write_json
    from ..design.rank import rank_by_network_onset
    from ..model.network import load_network

    check_network_options(args)
    net = load_network(args.engine)
    try:
        net.segment(args.segment)
    except KeyError:
        porous = [s.name for br in net.branches for s in br.segments if s.kind == "porous"]
        raise KeyError(f"{net.source}: no segment {args.segment!r}; give --segment, one of {porous}") from None
    changes = {}
    for t in args.set:
        name, sep, value = t.partition("=")
        if not sep:
            raise ValueError(f"--set {t!r}: expected NAME=VALUE, e.g. gas.p_mean=1e6")
        changes[name.strip()] = float(value)
    if changes:
        net = net.replace(**changes)
    res = rank_by_network_onset(
        mats,
        net,
        segment=args.segment,
        n_samples=args.samples if args.samples is not None else 30,
        seed=args.seed,
        T_max=args.T_ratio_max * net.gas.T_cold,
        amplitude=args.amplitude,
        catalogue=cat,
        device=args.device,
    )
    d = res.to_dict()
    d["engine_changes"] = changes
    d["materials_used"] = {m: cat[m].to_dict() for m in res.materials}
    write_json(out, d)
    _say(
        args, f"{'material':<12}{'T_hot/T_cold: nominal':>23}{'median':>9}{'5-95 %':>15}{'Edot [W]':>10}{'P(best)':>9}"
    )

    def fmt(v):
        return f"{v:.4g}" if v is not None else "none"

    for r in res.table:
        _say(
            args,
            f"{r['material']:<12}{fmt(r['T_ratio_nominal']):>23}{fmt(r['T_ratio_median']):>9}"
            f"{fmt(r['T_ratio_p05']) + '-' + fmt(r['T_ratio_p95']):>15}{fmt(r['Edot_produced_nominal_W']):>10}"
            f"{r['p_best']:9.2f}",
        )
    _say(args, f"wrote {out}")
    return 0


def add_rank_parser(sub) -> argparse.ArgumentParser:
    p = _common(
        sub.add_parser(
            "rank",
            help="rank stack materials by the gradient they reach or by the onset heat "
            "input of an engine, with uncertainty",
        )
    )
    p.add_argument(
        "--by",
        choices=("gradient", "onset"),
        default="gradient",
        help="gradient: stack gradient at --Q in --core; onset: onset heat input of --engine (default: %(default)s)",
    )
    p.add_argument(
        "--engine",
        default="standing_wave",
        help="--by onset: reference engine (TOML or bundled name) whose stack takes each material "
        "(default: %(default)s); a network (traveling_wave) ranks by the onset T_hot / T_cold",
    )
    p.add_argument(
        "--T-ratio-max",
        dest="T_ratio_max",
        type=float,
        default=4.0,
        help="--by onset, network: largest T_hot/T_cold searched (default: %(default)s)",
    )
    p.add_argument(
        "--amplitude",
        type=float,
        default=1e5,
        help="--by onset, network: |p| [Pa] at the network's first end for the segment's Edot (default: %(default)s)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        help="--by onset: NAME=VALUE changes the engine's core, e.g. gas.p_mean=1e6 (repeatable)",
    )
    p.add_argument(
        "--Q-max",
        dest="Q_max",
        type=float,
        default=200.0,
        help="--by onset: largest heat input searched [W] (default: %(default)s)",
    )
    p.add_argument(
        "--bracket",
        type=int,
        default=9,
        help="--by onset: heat inputs on [0, Q-max] bracketing the onset (default: %(default)s)",
    )
    p.add_argument("--materials", default=None, help="comma list of catalogue names (default: all)")
    p.add_argument("--Q", type=_floats, default=_floats("9"), help="heat inputs [W], list or start:stop:count")
    p.add_argument(
        "--core", default="rvc_foam", help="reference core whose stack takes each material (default: %(default)s)"
    )
    p.add_argument(
        "--segment",
        default="stack",
        help="the segment that takes each material (default: %(default)s; a network engine: its porous one, "
        "e.g. regenerator)",
    )
    p.add_argument("--catalogue", action="append", help="extra materials: a TOML catalogue or a fit.json (repeatable)")
    p.add_argument(
        "--samples",
        type=int,
        default=None,
        help="draws per material (default: 4000 by gradient, 400 by onset, 30 by a network's onset)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the material draws (default: %(default)s)")
    _add_T_limit(p, "temperature limit [K]: each material's share of draws whose T_max exceeds it is reported")
    p.add_argument(
        "-o",
        "--output",
        default="rank.json",
        help="output JSON (default: %(default)s); its figure STEM.png beside it" + CLAIM_HELP,
    )
    p.add_argument("--no-plots", action="store_true", help="skip the figure")
    p.set_defaults(func=cmd_rank)
    return p


# -- sweep -------------------------------------------------------------------------------
def cmd_sweep(args) -> int:
    from ..io import write_json
    from ..design.sweep import sweep

    if Path(args.output).suffix.lower() != ".nc":
        raise ValueError(
            f"-o {args.output}: the sweep is written as netCDF and its JSON summary beside it; give a .nc file name"
        )
    check_option(
        args.samples is None or args.samples >= 1, "--samples", args.samples, "expected a number of Sobol points >= 1"
    )
    check_option(args.chunk is None or args.chunk >= 1, "--chunk", args.chunk, "expected at least 1 point per launch")
    check_seed(args)
    objectives = _objectives(args.objectives)
    summary = Path(args.output).with_suffix(".json")
    claim_outputs(summary, why="the sweep's summary")
    space = _space(args, grid=args.samples is None)
    mode = "grid" if args.samples is None else "sobol"
    info = sweep(
        space,
        args.output,
        mode=mode,
        n_samples=args.samples,
        chunk=args.chunk,
        seed=args.seed,
        settings=_settings(args),
        progress=not args.quiet,
        reduce=args.reduce,
        raw=not args.no_raw,
        objectives=objectives,
    )
    meta = {
        "generator": f"{GENERATOR} sweep",
        "output": str(info.path),
        "mode": mode,
        "points": info.n_points,
        "seconds": info.seconds,
        "evaluations_per_hour": info.evaluations_per_hour,
        "chunks": info.chunks,
        "evaluation_seconds": info.evaluation_seconds,
        "write_seconds": info.write_seconds,
        "variables": space.describe(),
    }
    if info.reductions is not None:
        meta["reduce"] = args.reduce
        meta["raw"] = not args.no_raw
        meta["reductions"] = info.reductions
    write_json(summary, meta)
    _say(args, f"{info.n_points} points in {info.seconds:.1f} s ({info.evaluations_per_hour:.3g}/h); wrote {info.path}")
    return 0


def add_sweep_parser(sub) -> argparse.ArgumentParser:
    p = _common(
        sub.add_parser(
            "sweep",
            help="grid or quasi-random sweep streamed to a netCDF file",
            description="Grid: every --var NAME=LOW:HIGH:COUNT[:log] or NAME=v1,v2 is a dimension. "
            "With --samples N: N scrambled Sobol points over --var NAME=LOW:HIGH ranges.",
        )
    )
    _add_space_args(p)
    p.add_argument("--samples", type=int, default=None, help="quasi-random (Sobol) sweep of this many points")
    p.add_argument(
        "--chunk",
        type=int,
        default=None,
        help="points per launch and write (default: 2^20 on a GPU, 2^16 on the CPU, where a Ctrl-C waits "
        "for the launch in flight)",
    )
    p.add_argument(
        "--seed", type=int, default=0, help="seed of the scrambled Sobol points, with --samples (default: %(default)s)"
    )
    p.add_argument(
        "--reduce",
        default=None,
        help="reductions computed on the device while the sweep runs, written as groups of the file "
        "(xarray.open_dataset(FILE, group=NAME)): any of best (per variable level), top=K, pareto, "
        "histogram, quantiles, comma-separated, e.g. best,quantiles,histogram,pareto,top=100",
    )
    p.add_argument(
        "--no-raw",
        action="store_true",
        help="write the reductions alone, not every point's outputs (needs --reduce)",
    )
    p.add_argument(
        "--objectives",
        default="gradient,heat_leak",
        help="with --reduce: the objectives that best and top rank (the first) and pareto (the first two), "
        "each in its direction (default: %(default)s)",
    )
    p.add_argument(
        "-o",
        "--output",
        default="sweep.nc",
        help="output netCDF (default: %(default)s); its JSON summary STEM.json beside it" + CLAIM_HELP,
    )
    p.set_defaults(func=cmd_sweep)
    return p
