"""Sweeps: many independent simulated campaigns (simulate -> fit -> diagnose), one record each.

A sweep specification (TOML) crosses scenarios x effect magnitudes x campaign designs x seed
replicates::

    [sweep]
    name = "magnetic-power"
    seed = 2026             # root of the SeedSequence the replicates' seeds are spawned from
    replicates = 8
    threads = 1             # BLAS and statics threads per case (processes run side by side)

    [[study]]
    scenario = "quiet/magnetic-force"   # a scenario TOML path (relative to the spec) or name
    effect = "magnetic_force"            # the effect whose magnitude is swept
    parameter = "coil_moment_per_A"      # the parameter scaled (its scenario value, or default)
    magnitudes = [0.0, 0.02, 0.05]       # factors on it; 0 switches the effect off
    baseline = ["geometric_errors"]      # the fitted model (default: the scenario's [hidden])

    [designs.reduced]                    # campaign designs (default: one, "full", scale 1)
    scale = 0.3                          # fraction of the campaign's points
    campaign = { forces_N = [0.0, 2.0] } # keys of the scenario's [campaign] replaced

A scenario or a baseline that names a user effect (``file.py:Class``, a relative path from the
file that names it) runs that code only with the user's consent, as every reader of files does
(``trust_effects``; ``deltatwin sweep --trust-effects``): the specification is refused at load
otherwise, before any case runs.

A case is a scenario TOML with the parameter scaled and the design applied, and a seed. The
seed of replicate ``i`` is child ``i`` of ``SeedSequence(seed)`` (the same for every magnitude
and design: common random numbers make the differences between magnitudes sharper), so a
record depends on the case alone, not on where or in which order it ran. Each case is written as
one Parquet file, atomically, under ``effect=<name>/design=<name>/`` (a Hive-partitioned
dataset that ``pandas.read_parquet`` reads whole); a resumed sweep skips the cases whose file
exists. Cases run on a local process pool or on a dask.distributed cluster.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import tempfile
import time
import tomllib
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from deltatwin.files import atomic_write, toml_text
from deltatwin.twin.effects import LIBRARY, EffectError, effect_class, effect_spec
from deltatwin.twin.scenario import FORMAT_VERSION as SCENARIO_FORMAT_VERSION
from deltatwin.twin.scenario import SCENARIO_DIR, shipped_scenarios

log = logging.getLogger(__name__)

PARTITIONS = ("effect", "design")      # the dataset's folders: effect=<name>/design=<name>/
SPEC_TABLES = {"sweep": {"name", "seed", "replicates", "threads"}, "study": None, "designs": None}
STUDY_KEYS = {"scenario", "effect", "parameter", "magnitudes", "baseline"}
DESIGN_KEYS = {"scale", "campaign"}


class SweepError(ValueError):
    """A sweep specification or results folder that cannot be used (names file and key)."""


@dataclass(frozen=True)
class Case:
    """One simulated campaign. ``scenario`` is a resolved path; ``campaign`` the design's
    [campaign] replacements as sorted JSON; ``threads`` is how it runs, not what it is, and so
    is ``trust_effects`` (the user's consent to the user effects its scenario names, given when
    the specification was loaded)."""
    scenario: str
    effect: str
    parameter: str
    magnitude: float
    baseline: tuple
    design: str
    scale: float
    campaign: str
    replicate: int
    seed: int
    threads: int = 1
    trust_effects: bool = False

    @property
    def case_id(self) -> str:
        """SHA-256 (16 hex digits) of what the case is: the scenario's text, the swept
        parameter and magnitude, the baseline, the design, the seed."""
        what = dataclasses.asdict(self)
        what.pop("threads")
        what.pop("trust_effects")
        what["scenario"] = hashlib.sha256(Path(self.scenario).read_bytes()).hexdigest()
        return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]


@dataclass
class SweepSpec:
    name: str
    seed: int
    replicates: int
    threads: int
    cases: list

    @classmethod
    def load(cls, path, trust_effects=False) -> SweepSpec:
        """Read and check a sweep specification (see the module docstring). ``trust_effects``:
        the consent to run the user effects its scenarios and baselines name, as
        ``Scenario.load``'s (True, or the specs whose code may run)."""
        path = Path(path)
        f = str(path)
        if not path.is_file():
            raise SweepError(f"{f}: no such sweep specification file")
        try:
            doc = tomllib.loads(path.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise SweepError(f"{f}: not a valid TOML file ({exc})") from exc
        _keys(f, doc, SPEC_TABLES)
        sw = doc.get("sweep", {})
        _keys(f"{f} [sweep]", sw, SPEC_TABLES["sweep"])
        name = sw.get("name", path.stem)
        seed = _integer(f"{f} [sweep] seed", sw.get("seed", 0), 0)
        replicates = _integer(f"{f} [sweep] replicates", sw.get("replicates", 1), 1)
        threads = _integer(f"{f} [sweep] threads", sw.get("threads", 1), 1)
        designs = doc.get("designs", {"full": {"scale": 1.0}})
        if not isinstance(designs, dict) or not designs:
            raise SweepError(f"{f} [designs]: expected tables [designs.<name>] with scale = ...")
        checked = {}
        for dname, d in designs.items():
            w = f"{f} [designs.{dname}]"
            if not isinstance(d, dict):
                raise SweepError(f"{w}: expected a table (scale = ..., campaign = {{...}})")
            _keys(w, d, DESIGN_KEYS)
            scale = d.get("scale", 1.0)
            if isinstance(scale, bool) or not isinstance(scale, (int, float)) \
                    or not 0 < scale <= 1:
                raise SweepError(f"{w} scale = {scale!r}: expected a fraction in (0, 1]")
            camp = d.get("campaign", {})
            if not isinstance(camp, dict):
                raise SweepError(f"{w} campaign: expected a table of [campaign] keys")
            checked[dname] = (float(scale), json.dumps(camp, sort_keys=True))
        studies = doc.get("study")
        if not isinstance(studies, list) or not studies:
            raise SweepError(f"{f}: at least one [[study]] table is needed")
        seeds = [_seed(c) for c in np.random.SeedSequence(seed).spawn(replicates)]
        cases = []
        for i, st in enumerate(studies):
            w = f"{f} [[study]] #{i + 1}"
            _keys(w, st, STUDY_KEYS)
            scenario = _scenario_path(w, st.get("scenario"), path.parent)
            trusted = _consent(w, scenario, trust_effects)
            effect, parameter = st.get("effect"), st.get("parameter")
            if effect not in LIBRARY:
                raise SweepError(f"{w} effect = {effect!r}: not a library effect "
                                 f"({sorted(LIBRARY)})")
            names = [p.name for p in LIBRARY[effect].parameters]
            if parameter not in names:
                raise SweepError(f"{w} parameter = {parameter!r}: not a parameter of {effect} "
                                 f"({names})")
            mags = st.get("magnitudes")
            if not isinstance(mags, list) or not mags or not all(
                    isinstance(m, (int, float)) and not isinstance(m, bool)
                    and math.isfinite(m) and m >= 0 for m in mags):
                raise SweepError(f"{w} magnitudes = {mags!r}: expected a list of factors >= 0")
            baseline, named_in = st.get("baseline"), path.parent
            if baseline is None:
                hidden = tomllib.loads(Path(scenario).read_text(encoding="utf-8")).get("hidden")
                if not hidden:
                    raise SweepError(f"{w}: no baseline given and the scenario has no [hidden] "
                                     "baseline")
                baseline, named_in = hidden["baseline"], Path(scenario).parent
            if not isinstance(baseline, list) or effect in baseline:
                raise SweepError(f"{w} baseline = {baseline!r}: expected a list of effects "
                                 f"without the swept {effect!r}")
            baseline = _baseline_specs(w, baseline, named_in, trust_effects)
            for dname, (scale, camp) in checked.items():
                for m in mags:
                    for r, s in enumerate(seeds):
                        cases.append(Case(str(scenario), effect, parameter, float(m),
                                          tuple(baseline), dname, scale, camp, r, s, threads,
                                          trusted))
        ids = [c.case_id for c in cases]
        if len(set(ids)) != len(ids):
            raise SweepError(f"{f}: some cases appear twice (the same scenario, magnitude, "
                             "design and seed in two studies)")
        return cls(name, seed, replicates, threads, cases)


def _keys(where, table, allowed) -> None:
    if not isinstance(table, dict):
        raise SweepError(f"{where}: expected a table")
    extra = sorted(set(table) - set(allowed))
    if extra:
        raise SweepError(f"{where}: unknown key(s) {extra}; allowed: {sorted(allowed)}")


def _integer(where, value, minimum) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise SweepError(f"{where} = {value!r}: expected an integer >= {minimum}")
    return value


def _seed(child: np.random.SeedSequence) -> int:
    """The scenario seed (a non-negative int64) of a spawned SeedSequence."""
    return int(child.generate_state(1, np.uint64)[0] >> np.uint64(1))


def _consent(where, scenario: Path, trust_effects) -> bool:
    """Whether the cases of ``scenario`` may run the user effects it names: the scenario is read
    with the user's consent now, so a refusal comes before any case runs."""
    from deltatwin.twin.scenario import Scenario, ScenarioError

    try:
        Scenario.load(scenario, trust_effects=trust_effects)
    except ScenarioError as exc:
        raise SweepError(f"{where}: {exc}") from exc
    return bool(trust_effects)


def _baseline_specs(where, baseline: list, folder: Path, trust_effects) -> list[str]:
    """The baseline's effects as the cases name them: a library name, or the absolute spec of a
    user effect (a relative path from ``folder``, that of the file naming it), whose code runs
    only with the user's consent."""
    specs = []
    for name in baseline:
        if isinstance(name, str) and name in LIBRARY:
            specs.append(name)
            continue
        try:
            specs.append(effect_spec(effect_class(name, folder, f"{where} baseline",
                                                  trust_effects)))
        except EffectError as exc:
            raise SweepError(str(exc)) from exc
    return specs


def _scenario_path(where, name, folder: Path) -> Path:
    if not isinstance(name, str):
        raise SweepError(f"{where} scenario = {name!r}: expected a scenario path or name")
    for p in (folder / name, SCENARIO_DIR / f"{name}.toml"):
        if p.is_file():
            return p.resolve()
    raise SweepError(f"{where} scenario = {name!r}: no such file, and not a shipped scenario "
                     f"({', '.join(shipped_scenarios())})")


# ---------------------------------------------------------------------------------------------
# one case

def case_scenario_text(case: Case) -> str:
    """The case's scenario TOML: the swept parameter times the magnitude (0: the effect off),
    the design's [campaign] replacements, a robot file made absolute."""
    src = Path(case.scenario)
    doc = tomllib.loads(src.read_text(encoding="utf-8"))
    doc = {"format_version": SCENARIO_FORMAT_VERSION,
           **{k: v for k, v in doc.items() if k != "format_version"}}
    effects = doc.setdefault("effects", {})
    on = effects.setdefault("on", [])
    if case.magnitude == 0:
        effects["on"] = [e for e in on if e != case.effect]
        effects.pop(case.effect, None)
        if "hidden" in doc:
            doc["hidden"]["effects"] = [e for e in doc["hidden"]["effects"] if e != case.effect]
    else:
        if case.effect not in on:
            on.append(case.effect)
        table = effects.setdefault(case.effect, {})
        default = next(p.default for p in LIBRARY[case.effect].parameters
                       if p.name == case.parameter)
        table[case.parameter] = (np.asarray(table.get(case.parameter, default), float)
                                 * case.magnitude).tolist()
    doc.setdefault("campaign", {}).update(json.loads(case.campaign))
    robot = doc.get("robot", {}).get("file")
    if robot:
        doc["robot"]["file"] = str((src.parent / robot).resolve())
    # the case's TOML lies in another folder: a user effect's relative path made absolute
    effects["on"] = [_absolute_effect(e, src.parent) for e in effects["on"]]
    return toml_text(doc)


def _absolute_effect(spec, folder: Path):
    """``spec`` with a relative ``file.py:Class`` path taken from ``folder``."""
    target, sep, cls_name = spec.rpartition(":") if isinstance(spec, str) else ("", "", "")
    if sep and (target.endswith(".py") or "/" in target) and not Path(target).is_absolute():
        return f"{(folder / Path(target).expanduser()).resolve()}:{cls_name}"
    return spec


def case_scenario(case: Case):
    """The case's Scenario (loaded from a temporary copy of its TOML)."""
    from deltatwin.twin.scenario import Scenario

    with tempfile.TemporaryDirectory(prefix="deltatwin-case-") as tmp:
        path = Path(tmp) / Path(case.scenario).name
        path.write_text(case_scenario_text(case), encoding="utf-8")
        return Scenario.load(path, seed=case.seed, trust_effects=case.trust_effects)


def run_case(case: Case) -> dict:
    """Simulate the case's campaign, fit its baseline, diagnose: one record (module docstring)
    with its wall and CPU seconds. BLAS (threadpoolctl) and the batched kinematics and statics'
    chunk pool (models/batched.py THREADS) run on ``case.threads`` threads, so N workers side by
    side use N cores, not N x cores."""
    from threadpoolctl import threadpool_limits

    # loaded before the limit, so that the BLAS libraries they bring (scipy's) are limited too
    import deltatwin.calibration.diagnosis.diagnose  # noqa: F401
    import deltatwin.calibration.physics.fit  # noqa: F401
    from deltatwin.models import batched

    t0, cpu0 = time.perf_counter(), time.process_time()
    chunk_threads = batched.THREADS       # restored after the case: the caller's process keeps
    batched.THREADS = case.threads        # its own setting (tests run cases in-process)
    try:
        with threadpool_limits(limits=case.threads):
            rec = _simulate_fit_diagnose(case)
    finally:
        batched.THREADS = chunk_threads
    # how long, not what: left out of comparisons. CPU time is the process's: the case's own
    # when the worker runs one case at a time (a pool process; a Dask worker with --nthreads 1)
    rec["wall_s"] = time.perf_counter() - t0
    rec["cpu_s"] = time.process_time() - cpu0
    return rec


def _simulate_fit_diagnose(case: Case) -> dict:
    """The case's record without its timings (``run_case`` sets the threads around it)."""
    from deltatwin.calibration.diagnosis.diagnose import diagnose
    from deltatwin.calibration.errors import FitError
    from deltatwin.calibration.physics.fit import PhysicsFit

    sc = case_scenario(case)
    df, meta = sc.simulate(case.scale)
    noise_nm = sc.settings.noise_floor_m * 1e9
    rec = {"case_id": case.case_id, "scenario": sc.name, "effect": case.effect,
           "parameter": case.parameter, "magnitude": case.magnitude,
           "baseline": ",".join(case.baseline), "design": case.design, "scale": case.scale,
           "campaign": case.campaign, "replicate": case.replicate, "seed": case.seed,
           "n_rows": len(df), "noise_nm": noise_nm,
           "noise_floor_nm": max(meta["truth"]["noise_floor_nm"].values())}
    try:
        fit = PhysicsFit(list(case.baseline), noise_nm=noise_nm).fit(df, meta)
        d = diagnose(fit, "case")
    except FitError as exc:               # a campaign the baseline cannot fit is a result
        rec.update(status=f"fit failed: {exc}", **_no_diagnosis())
    else:
        ranks = [c["effect"] for c in d["ranking"]]
        mine = d["ranking"][ranks.index(case.effect)] if case.effect in ranks else None
        # a fit that stops short returns its best answer with the reason: kept, and left
        # out of the power rates (they count diagnoses of converged fits)
        rec.update(status="ok" if fit.converged_ else f"not converged: {fit.status_}",
                   val_err90_nm=d["val_err90_nm"],
                   n_identified=fit.identifiability_["n_identified_directions"],
                   missing_effect=d.get("missing_effect") or "",
                   named=d.get("missing_effect") == case.effect,
                   significant=bool(mine and mine["significant"]),
                   effect_rank=ranks.index(case.effect) + 1 if mine else -1,
                   effect_p_value=mine["p_value"] if mine else math.nan,
                   effect_delta_bic=mine["delta_bic"] if mine else math.nan,
                   effect_explained_fraction=mine["explained_fraction"] if mine else math.nan,
                   effect_val_err90_after_nm=mine["val_err90_after_nm"] if mine else math.nan)
    return rec


def _no_diagnosis() -> dict:
    return {"val_err90_nm": math.nan, "n_identified": -1, "missing_effect": "", "named": False,
            "significant": False, "effect_rank": -1, "effect_p_value": math.nan,
            "effect_delta_bic": math.nan, "effect_explained_fraction": math.nan,
            "effect_val_err90_after_nm": math.nan}


# ---------------------------------------------------------------------------------------------
# the results dataset

def case_file(out: Path, case: Case) -> Path:
    return out / f"effect={case.effect}" / f"design={case.design}" / f"case-{case.case_id}.parquet"


def write_record(out: Path, case: Case, rec: dict) -> Path:
    """One case's record as a Parquet file (partition columns live in the folder names)."""
    table = pa.Table.from_pylist([{k: v for k, v in rec.items() if k not in PARTITIONS}])
    return atomic_write(case_file(out, case), lambda tmp: pq.write_table(table, tmp))


def finished(out: Path) -> set[str]:
    """Case ids with a record in ``out``."""
    return {p.stem.removeprefix("case-") for p in Path(out).glob("*/*/case-*.parquet")}


def read_records(out) -> pd.DataFrame:
    """The sweep's records, one row per case, sorted by case id (partition columns as text)."""
    out = Path(out)
    if not any(out.glob("*/*/case-*.parquet")):
        raise SweepError(f"{out}: no sweep records (case-*.parquet under effect=*/design=*/)")
    df = pd.read_parquet(out)
    for c in PARTITIONS:
        df[c] = df[c].astype(str)
    return df.sort_values("case_id", ignore_index=True)


def run_sweep(spec: SweepSpec, out, workers: int = 1, scheduler: str | None = None,
              resume: bool = False, progress=None) -> dict:
    """Run the cases of ``spec`` not yet in ``out`` on ``workers`` local processes or on the
    dask.distributed scheduler at ``scheduler``; each record is written as it arrives.
    ``progress(done, total)`` is called after each case. Returns counts and timing."""
    out = Path(out)
    done = finished(out) if out.exists() else set()
    cases = spec.cases
    mine = {c.case_id for c in cases}
    if done and not resume:
        raise SweepError(f"{out}: already holds {len(done)} case records; pass --resume to "
                         "continue that sweep, or choose another results folder")
    todo = [c for c in cases if c.case_id not in done]
    skipped = len(cases) - len(todo)
    log.info("sweep %s: %d cases, %d already finished, %d to run", spec.name, len(cases),
             skipped, len(todo))
    load_start = _load_average()
    t0 = time.perf_counter()
    cpu = 0.0
    for i, (case, rec) in enumerate(_execute(todo, workers, scheduler), 1):
        write_record(out, case, rec)
        cpu += rec["cpu_s"]
        if progress:
            progress(i, len(todo))
    wall = time.perf_counter() - t0
    return {"cases": len(cases), "skipped": skipped, "ran": len(todo), "wall_s": wall,
            "cases_per_s": len(todo) / wall if todo and wall > 0 else math.nan,
            "cpu_s_per_case": cpu / len(todo) if todo else math.nan,
            "load_average_start": load_start, "load_average_end": _load_average(),
            "foreign_records": len(done - mine)}


def _load_average() -> float:
    """The machine's 1-minute load average (NaN where the system has none): a throughput
    figure on shared cores means little without it."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return math.nan


def _execute(cases: list, workers: int, scheduler: str | None):
    """(case, record) pairs as the cases finish."""
    if not cases:
        return
    if scheduler:
        from distributed import Client
        from distributed import as_completed as dask_completed

        with Client(scheduler) as client:
            futures = client.map(run_case, cases, pure=False)
            case_of = {f.key: c for f, c in zip(futures, cases)}
            for fut, rec in dask_completed(futures, with_results=True):
                yield case_of[fut.key], rec
        return
    # spawn: a fresh interpreter per worker (no forked copy of a threaded parent)
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
        futures = {pool.submit(run_case, c): c for c in cases}
        for fut in as_completed(futures):
            yield futures[fut], fut.result()


TIMING_COLUMNS = ("wall_s", "cpu_s")


def deterministic_columns(df: pd.DataFrame) -> list[str]:
    """The record's columns that depend on the case alone (all but the timings)."""
    return [c for c in df.columns if c not in TIMING_COLUMNS]

