"""The environment model manager (seed §2.1, §3.5): continuous correction of the model from scans.

Each batch of scans (files appearing in a folder, or :meth:`ModelManager.update` calls) updates
the estimate, warm-started from the current one, with the previous posterior carried as a prior
in information form (Λ, m) — widened by the process noise, so the estimate tightens over batches
and still follows slow drift.  After each update the manager

* appends one line to the **journal** ``history.jsonl`` (estimate, σ, χ², time, the posterior's
  mean and information, the files; written with one ``write`` and ``fsync``: the commit point),
* replaces the **snapshot** ``state.json`` atomically (the last accepted state),
* replaces the **calibrated model** ``<model>.calibrated.mdl`` atomically (never the input),
* flags a **drift** (an unknown moved more than ``k`` σ of the previous state, process noise
  included) and names each **structural misfit** (an object whose points no longer fit its
  shape, :class:`mbcal.range.fit.Misfit`).

Killed at any moment (kill -9), it loses no accepted update and leaves no half-written file:
a journal line is complete or ignored (a torn last line is cut off on restart), the other files
are renamed into place, and leftover temporary files are removed.  A restart resumes from the
journal (the snapshot is checked against it).
"""

from __future__ import annotations

import fnmatch
import json
import math
import os
import stat
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mbcal.errors import MbcalError, OutputError
from mbcal.export.mdl import write_calibrated_model
from mbcal.language.load import load_model
from mbcal.language.model import Model
from mbcal.outputs import atomic_write, check_output_folder, finite_or_null, make_output_folder
from mbcal.range.fit import FitOptions, Prior, ScanFit, fit_scans
from mbcal.range.readers import CLOUD_SUFFIXES, DEPTH_SUFFIXES, not_a_scan, write_ply
from mbcal.range.scans import Scan, load_scan
from mbcal.units import at_least

__all__ = ["ModelManager", "Update", "fit_files", "SCAN_SUFFIXES"]

SCAN_SUFFIXES = tuple(dict.fromkeys(CLOUD_SUFFIXES + DEPTH_SUFFIXES))


@dataclass
class Update:
    """One update of the manager: the fit, whether it was accepted, drifts and misfits."""

    seq: int
    time: float
    values: dict[str, float]
    std: dict[str, float]
    chi2: float
    reduced_chi2: float
    points: int
    outliers: int
    accepted: bool
    drift: list[str] = field(default_factory=list)
    misfits: list[str] = field(default_factory=list)
    files: list[str] = field(default_factory=list)
    mean: list[float] = field(default_factory=list)
    information: list[list[float]] = field(default_factory=list)
    elapsed: float = 0.0
    error: str = ""
    """Why the files could not be read (then nothing was fitted: the update is rejected)."""
    stamp: list[int] = field(default_factory=list)
    """Size and modification time (ns) of the file when it was read (by the watch): one that could
    not be read is tried again once it changes, one that was fitted is taken again once it changes
    (a copy that paused half-way and went on)."""
    doubts: list[str] = field(default_factory=list)
    """Why a fitted update was rejected: the scan fit's verdict (:attr:`ScanFit.doubts`)."""

    def to_json(self) -> dict[str, Any]:
        """The update as strict JSON: a σ that is infinite (an unknown no scan determines) and the
        χ² of a rejected update without a fit (NaN) are null."""
        return finite_or_null(dict(self.__dict__))

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> Update:
        fields = {k: d[k] for k in Update.__dataclass_fields__ if k in d}
        if "std" in fields:  # null: infinite (see to_json)
            fields["std"] = {k: math.inf if v is None else v for k, v in fields["std"].items()}
        for name in ("chi2", "reduced_chi2"):
            if name in fields and fields[name] is None:
                fields[name] = math.nan
        return Update(**fields)


def _outputs(fit: ScanFit, model: Model, out: Path, stem: str, note: Sequence[str]) -> list[Path]:
    """The calibrated model, the outliers PLY and the report JSON, each written atomically."""
    make_output_folder(out)  # removed again, when empty, if the command fails (all_or_nothing)
    written = []
    mdl, ply, rep = (out / name for name in _fit_outputs(stem))
    write_calibrated_model(model, fit.values, mdl, std=fit.std, note=list(note))
    written.append(mdl)
    write_ply(ply, fit.outlier_points, np.tile(np.array([[230, 40, 40]], dtype=np.uint8), (fit.n_outliers, 1)))
    written.append(ply)
    atomic_write(rep, json.dumps(fit.to_json(), indent=2, allow_nan=False) + "\n")
    written.append(rep)
    return written


def _check_out_dir(
    out: Path, inputs: Sequence[str | os.PathLike], outputs: Sequence[str], *, make: bool = True
) -> None:
    """``--out`` must be a folder where none of the files written (``outputs``: names in it) is
    an input; other files there, inputs too, stay untouched (a scan beside the results is no
    reason to refuse: a folder that merely held an input was refused though no name collided).
    ``make``: made now (the manager's journal needs it), else only checked (``mbcal fit`` makes it
    when it writes: a fit that fails leaves no empty folder behind)."""
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out} is a file; --out needs a folder")
    resolved = {Path(i).resolve() for i in inputs}
    for name in outputs:
        target = out / name
        if target.resolve() in resolved:
            raise OutputError(
                f"--out {out}: the output {target} would replace the input of that name; choose another "
                "folder (inputs are never overwritten)"
            )
    if not make:
        check_output_folder(out, "--out")
        if not out.exists():
            return
    out.mkdir(parents=True, exist_ok=True)


def _fit_outputs(stem: str) -> list[str]:
    """The names ``mbcal fit`` writes into ``--out`` (:func:`_outputs`)."""
    return [f"{stem}.calibrated.mdl", f"{stem}.outliers.ply", f"{stem}.fit.json"]


def fit_files(
    model_path: str | os.PathLike,
    scan_paths: Sequence[str | os.PathLike],
    estimate: Sequence[str],
    options: FitOptions | None = None,
    *,
    out: str | os.PathLike | None = None,
    sensor: str | None = None,
    frame: str | None = None,
    sigma: float | None = None,
) -> tuple[ScanFit, list[Path]]:
    """``mbcal fit``: read the model and scans, fit, and write the outputs into ``out``."""
    model = load_model(model_path)
    scans = [load_scan(p, model, sensor=sensor, frame=frame, sigma=sigma) for p in scan_paths]
    if out is not None:
        outputs = _fit_outputs(Path(model_path).stem)
        _check_out_dir(Path(out), [model_path, *scan_paths, *model.files], outputs, make=False)
    fit = fit_scans(model, scans, estimate, options)
    written: list[Path] = []
    if out is not None:
        note = [f"estimated by 'mbcal fit' from {', '.join(str(p) for p in scan_paths)}"]
        if not fit.ok:  # a model written from a fit not to be trusted says so where it is read (as solve's)
            note.append("NOT A TRUSTWORTHY FIT: " + "; ".join(fit.doubts))
        written = _outputs(fit, model, Path(out), Path(model_path).stem, note)
    return fit, written


class ModelManager:
    """Keeps a model calibrated from a stream of scans (see the module doc).

    Parameters
    ----------
    model_path : path
        The input model (never written).
    out : path
        Folder of the journal, the snapshot and the calibrated model.
    estimate : sequence of str
        Names or glob patterns of the unknowns.
    options : FitOptions, optional
    drift_k : float
        A drift is flagged when an unknown moves more than this many σ of the previous state.
    process_noise : mapping, optional
        Glob pattern → σ (SI) of the change expected per update (a lever that moves, a slowly
        sagging shelf); added to the prior's covariance before each update.
    sensor, frame, sigma
        How scan files are read (see :func:`mbcal.range.scans.load_scan`).
    """

    JOURNAL = "history.jsonl"
    SNAPSHOT = "state.json"

    def __init__(
        self,
        model_path: str | os.PathLike,
        out: str | os.PathLike,
        estimate: Sequence[str],
        options: FitOptions | None = None,
        *,
        drift_k: float = 3.0,
        process_noise: Mapping[str, float] | None = None,
        sensor: str | None = None,
        frame: str | None = None,
        sigma: float | None = None,
    ):
        self.model_path = Path(model_path)
        self.model = load_model(model_path)
        self.out = Path(out)
        self.estimate = [estimate] if isinstance(estimate, str) else list(estimate)
        if not self.estimate:
            raise MbcalError("the model manager needs unknowns to estimate (estimate: names or globs)")
        for pattern in self.estimate:
            if not self.model.match_params(pattern):
                self.model.param_index(pattern)  # raises, with the closest names
        self.options = options or FitOptions()
        if not at_least(drift_k, 0.0, strict=True):
            raise MbcalError(f"drift_k must be a number of σ > 0, got {drift_k!r}")
        if sigma is not None and not at_least(sigma, 0.0, strict=True):
            raise MbcalError(f"sigma must be a positive number of metres, got {sigma!r}")
        if sensor is not None:
            self.model.resolve("range", sensor)  # raises for a name no range sensor has
        if frame is not None and frame != "world":
            self.model.resolve("frame", frame)
        self.drift_k = drift_k
        self.set_process_noise(process_noise or {})  # checked before the folder is made
        outputs = [self.JOURNAL, self.SNAPSHOT, f"{self.model_path.stem}.calibrated.mdl"]
        _check_out_dir(self.out, [self.model_path, *self.model.files], outputs)
        self.sensor, self.frame, self.sigma = sensor, frame, sigma
        self.history: list[Update] = []
        self.prior: Prior | None = None
        self._skipped: dict[str, list[int]] = {}  # files that are no scans (not_a_scan), with their stamp
        self._resume()

    def set_process_noise(self, process_noise: Mapping[str, float]) -> None:
        """σ per update by pattern (SI units); each pattern must match an estimated unknown."""
        estimated = list(dict.fromkeys(n for e in self.estimate for n in self.model.match_params(e)))
        for pattern, s in process_noise.items():
            if not set(self.model.match_params(pattern)) & set(estimated):
                raise MbcalError(
                    f"process noise for '{pattern}': no estimated unknown matches it",
                    hint=f"the unknowns: {', '.join(estimated) or 'none'}",
                )
            if not (np.isfinite(s) and s >= 0):
                raise MbcalError(f"process noise for '{pattern}' must be a finite σ ≥ 0, got {s}")
        self.process_noise = dict(process_noise)

    # ---- persistence ----------------------------------------------------------------------------------

    @property
    def journal(self) -> Path:
        return self.out / self.JOURNAL

    @property
    def model_out(self) -> Path:
        return self.out / f"{self.model_path.stem}.calibrated.mdl"

    def _resume(self) -> None:
        for stale in self.out.glob(".*.part"):  # temporary files of a write cut short by a kill
            stale.unlink(missing_ok=True)
        if not self.journal.exists():
            return
        raw = self.journal.read_bytes()
        good = raw.rfind(b"\n") + 1
        if good < len(raw):  # a torn last line (killed mid-append): not committed, cut it off
            with open(self.journal, "r+b") as f:
                f.truncate(good)
                f.flush()
                os.fsync(f.fileno())
        for k, line in enumerate(raw[:good].decode("utf-8").splitlines(), start=1):
            if not line.strip():
                continue
            try:
                self.history.append(Update.from_json(json.loads(line)))
            except (ValueError, TypeError) as err:
                raise MbcalError(f"{self.journal}:{k}: not a journal entry ({err})") from None
        last = self.last_accepted
        if last is not None:
            self.prior = Prior(tuple(last.values), np.asarray(last.mean), np.asarray(last.information))
            self._write_state(last)

    @property
    def last_accepted(self) -> Update | None:
        for u in reversed(self.history):
            if u.accepted:
                return u
        return None

    def _append(self, update: Update) -> None:
        line = (json.dumps(update.to_json(), allow_nan=False) + "\n").encode("utf-8")
        fd = os.open(self.journal, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line)
            os.fsync(fd)
        finally:
            os.close(fd)

    def _write_state(self, u: Update) -> None:
        snap = {"seq": u.seq, "values": u.values, "std": u.std, "mean": u.mean, "information": u.information}
        atomic_write(self.out / self.SNAPSHOT, json.dumps(finite_or_null(snap), allow_nan=False) + "\n")
        stamp = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(u.time))
        note = [f"kept by the model manager: update {u.seq} of {stamp} UTC"]
        write_calibrated_model(self.model, u.values, self.model_out, std=u.std, note=note)

    # ---- updates ---------------------------------------------------------------------------------------

    @property
    def processed(self) -> dict[str, list[int]]:
        """The files taken — fitted, accepted or not (a file that could not be read is not) — with
        their size and time when taken (empty from a journal older than that record): a file that
        changes after it was taken (a copy that paused half-way) is taken again."""
        return {f: list(u.stamp) for u in self.history if not u.error for f in u.files}

    @property
    def unreadable(self) -> dict[str, list[int]]:
        """Files that could not be read, with their size and time then (the latest attempt)."""
        return {f: u.stamp for u in self.history if u.error for f in u.files}

    def _widened_prior(self) -> Prior | None:
        """The previous posterior with the process noise added to its covariance."""
        if self.prior is None or not self.process_noise:
            return self.prior
        names = list(self.prior.names)
        q = np.zeros(len(names))
        for pattern, s in self.process_noise.items():
            for j, n in enumerate(names):
                if fnmatch.fnmatchcase(n, pattern):
                    q[j] = float(s)
        Lam = np.asarray(self.prior.information)
        cov = np.linalg.pinv(Lam) + np.diag(q**2)
        return Prior(self.prior.names, self.prior.mean, np.linalg.inv(cov))

    def update(self, scans: Sequence[Scan], files: Sequence[str] = (), stamp: Sequence[int] = ()) -> Update:
        """Fit one batch, record it, and (when accepted) write the state and the calibrated model."""
        prior = self._widened_prior()
        last = self.last_accepted
        initial = dict(last.values) if last is not None else None
        fit = fit_scans(self.model, scans, self.estimate, self.options, initial=initial, prior=prior)
        std = fit.std
        drift = []
        if last is not None and prior is not None:
            prev_sd = np.sqrt(np.clip(np.diag(np.linalg.pinv(np.asarray(prior.information))), 0, None))
            for j, n in enumerate(prior.names):
                if n in fit.values and prev_sd[j] > 0:
                    moved = abs(fit.values[n] - last.values[n])
                    if moved > self.drift_k * prev_sd[j]:
                        drift.append(f"{n} moved {moved / prev_sd[j]:.1f}σ since update {last.seq}")
        # the verdict of `mbcal fit` itself (reduced χ², structural misfits included): an update that
        # fit would call NOT trustworthy replaced the state and the calibrated model
        accepted = fit.ok
        u = Update(
            seq=len(self.history) + 1,
            time=time.time(),
            values=fit.values,
            std=std,
            chi2=fit.chi2,
            reduced_chi2=fit.reduced_chi2,
            points=len(fit.points),
            outliers=fit.n_outliers,
            accepted=bool(accepted),
            drift=drift,
            misfits=[m.message(fit.outlier_sigma, float(np.median(fit.sigma))) for m in fit.structural],
            files=[str(f) for f in files],
            mean=[float(v) for v in fit.x],
            information=np.asarray(fit.information).tolist(),
            elapsed=fit.elapsed,
            doubts=fit.doubts,
            stamp=[int(v) for v in stamp],
        )
        self._append(u)  # the commit point
        self.history.append(u)
        if accepted:
            self.prior = fit.prior()
            self._write_state(u)
        return u

    def update_files(self, paths: Sequence[str | os.PathLike], stamp: Sequence[int] = ()) -> Update:
        """One update from these files; ``stamp``: the size and time of a single file as the watch
        saw it (recorded, so that the file is taken again when it changes)."""
        scans = [load_scan(p, self.model, sensor=self.sensor, frame=self.frame, sigma=self.sigma) for p in paths]
        return self.update(scans, [str(Path(p).resolve()) for p in paths], stamp)

    def _unreadable(self, path: Path, stamp: list[int], err: MbcalError) -> Update:
        """Record a scan file that cannot be read (a rejected update without a fit), so that the
        watch goes on with the next file and a restart does not stop at it again."""
        last = self.last_accepted
        u = Update(
            seq=len(self.history) + 1,
            time=time.time(),
            values=dict(last.values) if last is not None else {},
            std=dict(last.std) if last is not None else {},
            chi2=math.nan,  # nothing was fitted
            reduced_chi2=math.nan,
            points=0,
            outliers=0,
            accepted=False,
            files=[str(path.resolve())],
            error=str(err),
            stamp=stamp,
        )
        self._append(u)
        self.history.append(u)
        return u

    def watch(
        self,
        folder: str | os.PathLike,
        *,
        poll: float = 1.0,
        once: bool = False,
        settle: float = 0.5,
        report: Callable[[Update], None] | None = None,
        max_updates: int | None = None,
        note: Callable[[str], None] | None = None,
    ) -> int:
        """Process scan files appearing in ``folder`` (oldest name first), one update per file.

        ``once``: process what is there and return (after waiting for the files still being
        written); otherwise poll every ``poll`` s until interrupted.  A file is taken when it was
        last modified ``settle`` s ago or more, or once its size has not changed for ``settle`` s
        (a clock that disagrees with the file system's).  Returns the number of updates made.

        A file of a scan's suffix that cannot be a scan by its kind (:func:`not_a_scan`: an 8-bit
        photo, a README or log as text) is skipped: no update, ``note`` gets one line for it (again
        only when it changes); a broken file of a scan's kind is a rejected update.  With ``once``,
        a folder without a file of a scan's suffix gets one ``note`` saying so.
        """
        src = Path(folder)
        if not src.is_dir():
            raise MbcalError(f"{src}: not a folder (--scans needs a folder of scan files)")
        done, unreadable = self.processed, self.unreadable
        count = 0
        sizes: dict[Path, tuple[int, float]] = {}
        while True:
            writing = False  # a file seen still being written: --once waits for it
            scans = others = 0  # files of a scan's suffix, and the other files (not looked at)
            for p in sorted(src.iterdir()):
                if p.suffix.lower() not in SCAN_SUFFIXES or p.name.startswith("."):
                    others += not p.name.startswith(".") and not p.is_dir()
                    continue
                scans += 1
                taken = done.get(str(p.resolve()))
                if taken == []:
                    continue  # taken before stamps were recorded, never again
                try:
                    info = p.stat()
                except OSError:  # a link to nothing (a rejected update), or a file removed meanwhile
                    if not p.is_symlink():
                        continue
                    stamp = [-1, p.lstat().st_mtime_ns]
                    if unreadable.get(str(p.resolve())) == stamp:
                        continue
                    u = self._unreadable(p, stamp, MbcalError(f"{p}: a link to a file that does not exist"))
                    unreadable[str(p.resolve())] = stamp
                else:
                    if not stat.S_ISREG(info.st_mode):
                        continue  # a folder that happens to end in .ply: no scan
                    stamp = [info.st_size, info.st_mtime_ns]
                    if unreadable.get(str(p.resolve())) == stamp or taken == stamp:
                        continue  # could not be read, or taken, and has not changed since
                    size = info.st_size
                    seen = sizes.get(p)
                    now = time.monotonic()
                    rested = seen is not None and seen[0] == size and now - seen[1] >= settle
                    if not rested and time.time() - info.st_mtime_ns / 1e9 < settle:
                        if seen is None or seen[0] != size:
                            sizes[p] = (size, now)
                        writing = True
                        continue
                    if self._skipped.get(str(p.resolve())) == stamp:
                        continue
                    why = not_a_scan(p)
                    if why is not None:  # an unrelated file beside the scans: no update, one note
                        self._skipped[str(p.resolve())] = stamp
                        if note is not None:
                            note(f"{p}: skipped, not a scan: {why}")
                        continue
                    try:
                        u = self.update_files([p], stamp)
                        done[str(p.resolve())] = stamp
                    except MbcalError as err:  # one bad file does not stop the watch (it is in the journal)
                        u = self._unreadable(p, stamp, err)
                        unreadable[str(p.resolve())] = stamp
                count += 1
                if report is not None:
                    report(u)
                if max_updates is not None and count >= max_updates:
                    return count
            if once and not writing:
                if not scans and note is not None:  # a wrong folder, or scans of a suffix not read: not silence
                    beside = f"; {others} other file{'s' * (others != 1)} not looked at" if others else ""
                    note(f"{src}: no scan found (scans are {', '.join(SCAN_SUFFIXES)} files){beside}")
                return count
            time.sleep(min(poll, settle) if once else poll)
