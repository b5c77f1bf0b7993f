"""OPC 40100-1 results from the service's events: a ResultDataType for every pick attempt's
verdict and every job's end (cell.service.results.VisionResult), and the conversions the
Machine Vision server answers with (ResultDataType, the recipe and configuration ids,
ResultContent as KeyValuePairs). The structure classes are asyncua's, made from the
Machine Vision NodeSet's DataTypeDefinitions when the address space is loaded."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from asyncua import ua

from cell.core.events import CalibrationInstalled, ConfigLoaded, Event, JobEnded, JobStarted, PickVerified, TargetChosen
from cell.recipes import RecipeBook, RecipeError
from cell.service.results import JOB_STATES, PICK_STATES, ResultStore, VisionResult
from cell.service.ua_values import mv_struct

_T = ua.VariantType


@dataclass
class _Job:
    job_id: str
    start: datetime
    recipe_id: str
    request: dict[str, Any]


class ResultMaker:
    """Turns the service's events into results (on the subscriber thread)."""

    def __init__(self, store: ResultStore, recipes: RecipeBook, simulated: bool):
        self.store, self.recipes, self.simulated = store, recipes, simulated
        self.jobs: dict[str, _Job] = {}
        self.targets: dict[str, datetime] = {}
        self.calibration_id = ""

    def on_event(self, e: Event) -> VisionResult | None:
        if isinstance(e, ConfigLoaded):
            self.simulated = e.dry_run
        elif isinstance(e, CalibrationInstalled):
            self.calibration_id = e.calibration_id
        elif isinstance(e, JobStarted) and e.job_id:
            self.jobs[e.job_id] = _Job(e.job_id, e.time_utc, e.recipe, dict(e.arguments))
            while len(self.jobs) > 16:
                self.jobs.pop(next(iter(self.jobs)))
        elif isinstance(e, TargetChosen):
            self.targets[e.pick_id] = e.time_utc
            while len(self.targets) > 256:
                self.targets.pop(next(iter(self.targets)))
        elif isinstance(e, PickVerified):
            return self._add(self._pick(e))
        elif isinstance(e, JobEnded) and e.job_id:
            return self._add(self._job_end(e))
        return None

    def _add(self, result: VisionResult) -> VisionResult:
        self.store.add(result)
        return result

    def _common(self, job_id: str, end: datetime, start: datetime | None) -> dict[str, Any]:
        job = self.jobs.get(job_id)
        request = job.request if job else {}
        recipe = job.recipe_id if job else ""
        return {
            "job_id": job_id,
            "creation_time": end,
            "start_time": start or end,
            "processing_ms": max(0.0, ((end - start).total_seconds() * 1000.0) if start else 0.0),
            "is_simulated": self.simulated,
            "recipe_id": recipe,
            "recipe_sha256": self._recipe_sha(recipe),
            "configuration_id": self.calibration_id,
            "meas_id": str(request.get("meas_id", "")),
            "part_id": str(request.get("part_id", "")),
            "product_id": str(request.get("product_id", "")),
        }

    def _recipe_sha(self, recipe_id: str) -> str:
        if not recipe_id:
            return ""
        try:
            return self.recipes.sha256(recipe_id)
        except RecipeError:
            return ""

    def _pick(self, e: PickVerified) -> VisionResult:
        job_id = e.job_id or e.pick_id.rsplit("/", 1)[0]
        start = self.targets.pop(e.pick_id, None) or (e.time_utc - timedelta(milliseconds=e.cycle_ms))
        self.calibration_id = e.calibration_id or self.calibration_id
        content = {
            "Class": e.cls,
            "Outcome": e.result,
            "TableMm": [float(v) for v in e.table_mm],
            "RobotMm": [float(v) for v in e.robot_mm],
            "JawAngleDeg": float(e.jaw_angle_deg) if e.jaw_angle_deg is not None else 0.0,
            "PixelPx": [float(v) for v in e.pixel],
            "Track": int(e.track),
            "Attempt": int(e.attempt),
            "CycleMs": float(e.cycle_ms),
        }
        common = self._common(job_id, e.time_utc, start)
        return VisionResult(
            e.pick_id, kind="pick", result_state=PICK_STATES.get(e.result, 4), content=content, **common
        )

    def _job_end(self, e: JobEnded) -> VisionResult:
        job = self.jobs.get(e.job_id or "")
        content: dict[str, Any] = {"Mode": e.mode, "Outcome": e.outcome, "Reason": e.reason}
        content.update({_camel(k): int(v) for k, v in e.counts.items() if isinstance(v, int | float)})
        common = self._common(e.job_id or "", e.time_utc, job.start if job else None)
        self.jobs.pop(e.job_id or "", None)
        return VisionResult(
            f"{e.job_id}/end", kind="job", result_state=JOB_STATES.get(e.outcome, 4), content=content, **common
        )


def _camel(name: str) -> str:
    return "".join(p[:1].upper() + p[1:] for p in name.split("_"))


def internal_id(recipe_id: str, sha256_hex: str) -> Any:
    return mv_struct("RecipeIdInternalDataType")(
        Id=recipe_id,
        Hash=bytes.fromhex(sha256_hex) if sha256_hex else None,
        HashAlgorithm="SHA-256" if sha256_hex else None,
    )


def external_id(recipe_id: str, sha256_hex: str) -> Any:
    return mv_struct("RecipeIdExternalDataType")(
        Id=recipe_id,
        Hash=bytes.fromhex(sha256_hex) if sha256_hex else None,
        HashAlgorithm="SHA-256" if sha256_hex else None,
    )


def _configuration_id(calibration_id: str) -> Any:
    return mv_struct("ConfigurationIdDataType")(
        Id=calibration_id or "none", Description=ua.LocalizedText("the calibration in use")
    )


def _content(content: dict[str, Any]) -> list[ua.Variant]:
    """ResultContent: one KeyValuePair per field (Key in the application namespace's words)."""
    out = []
    for key, value in content.items():
        if isinstance(value, list):
            inner = ua.Variant([float(v) for v in value], _T.Double, is_array=True)
        elif isinstance(value, bool):
            inner = ua.Variant(value, _T.Boolean)
        elif isinstance(value, int):
            inner = ua.Variant(value, _T.Int32)
        elif isinstance(value, float):
            inner = ua.Variant(value, _T.Double)
        else:
            inner = ua.Variant(str(value), _T.String)
        out.append(ua.Variant(ua.KeyValuePair(Key=ua.QualifiedName(key, 0), Value=inner), _T.ExtensionObject))
    return out


def result_data(r: VisionResult) -> Any:
    """The result as OPC 40100-1's ResultDataType."""
    times = mv_struct("ProcessingTimesDataType")(
        StartTime=r.start_time, EndTime=r.creation_time, ProcessingDuration=float(r.processing_ms)
    )
    return mv_struct("ResultDataType")(
        ResultId=mv_struct("ResultIdDataType")(Id=r.result_id),
        IsPartial=False,
        IsSimulated=r.is_simulated,
        ResultState=r.result_state,
        MeasId=mv_struct("MeasIdDataType")(Id=r.meas_id) if r.meas_id else None,
        PartId=mv_struct("PartIdDataType")(Id=r.part_id) if r.part_id else None,
        ExternalRecipeId=external_id(r.recipe_id, r.recipe_sha256) if r.recipe_id else None,
        InternalRecipeId=internal_id(r.recipe_id, r.recipe_sha256),
        ProductId=mv_struct("ProductIdDataType")(Id=r.product_id) if r.product_id else None,
        InternalConfigurationId=_configuration_id(r.configuration_id),
        JobId=mv_struct("JobIdDataType")(Id=r.job_id),
        CreationTime=r.creation_time,
        ProcessingTimes=times,
        ResultContent=_content(r.content),
    )


def result_message(r: VisionResult) -> str:
    c = r.content
    if r.kind == "pick":
        x, y = c.get("TableMm", [0.0, 0.0])
        return f"{r.result_id}: {c.get('Class')} {c.get('Outcome')} at table ({x:.1f}, {y:.1f}) mm"
    return f"{r.result_id}: job {c.get('Outcome')} ({c.get('Reason', '')})"
