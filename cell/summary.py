"""The end-of-run summary, and the same counts recomputed from an audit log so the two can
be checked against each other (a summary that disagrees with its log is a bug).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from cell.wording import plural

# picked: per class; every other key a number.
Counts = dict[str, int | dict[str, int]]
COUNT_KEYS = ("picked", "misses", "retries", "failed", "unreachable", "rehearsed", "attempts", "unknown_left")


@dataclass
class Summary:
    outcome: str = "running"  # done | fault | stopped
    reason: str = ""
    exit_code: int = 0
    picked: dict[str, int] = field(default_factory=dict)  # per class
    misses: int = 0  # verifications that found the part still there
    retries: int = 0  # attempts after the first at the same part
    failed: int = 0  # parts given up after max_retries
    unreachable: int = 0  # parts refused before motion
    rehearsed: int = 0  # dry run with nothing moving: targets sent, nothing verified
    attempts: int = 0
    unknown_left: int = 0  # parts in the last frame that are not picked (washers, debris)
    frames: int = 0
    wall_s: float = 0.0
    capture_s: float = 0.0  # inside camera.capture(): the simulated camera's rendering
    arm_s: float = 0.0  # inside arm calls (a real arm's motion)
    paused_s: float = 0.0
    motion_sim_s: float = 0.0  # the simulated arm's motion time (not spent in wall time)
    software_s: float = 0.0  # everything else: locate, plan, verify, logging
    locate_s: float = 0.0  # the part of software_s spent finding parts in frames

    @property
    def software_ms_per_pick(self) -> float:
        return 1e3 * self.software_s / max(self.attempts, 1)

    @property
    def wall_ms_per_pick(self) -> float:
        return 1e3 * self.wall_s / max(self.attempts, 1)

    @property
    def motion_s_per_pick(self) -> float:
        return (self.motion_sim_s or self.arm_s) / max(self.attempts, 1)

    def counts(self) -> Counts:
        return {k: getattr(self, k) for k in COUNT_KEYS}

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d.update(
            software_ms_per_pick=round(self.software_ms_per_pick, 3),
            wall_ms_per_pick=round(self.wall_ms_per_pick, 3),
            motion_s_per_pick=round(self.motion_s_per_pick, 3),
        )
        return d

    def lines(self) -> list[str]:
        picked = ", ".join(plural(n, cls) for cls, n in sorted(self.picked.items())) or "nothing"
        headline = "DONE WITH FAILURES" if self.outcome == "done" and self.exit_code else self.outcome.upper()
        out = [
            f"{headline}: {self.reason}",
            f"picked {picked}; {plural(self.misses, 'miss', 'misses')}, {plural(self.retries, 'retry', 'retries')}, "
            f"{self.failed} failed, {self.unreachable} unreachable, {plural(self.unknown_left, 'unknown part')} left",
        ]
        if self.rehearsed:
            out.append(f"rehearsed {plural(self.rehearsed, 'pick')} (nothing moved, nothing verified)")
        if not self.attempts:
            out.append(f"no pick attempts; {self.wall_s:.1f} s wall, software {1e3 * self.software_s:.1f} ms")
            return out
        out.append(
            f"{plural(self.attempts, 'pick attempt')} in {self.wall_s:.1f} s wall: {self.wall_ms_per_pick:.0f} ms per pick, "
            f"of which software {self.software_ms_per_pick:.1f} ms (locate "
            f"{1e3 * self.locate_s / self.attempts:.1f} ms, plan, verify, log) and "
            f"camera {1e3 * self.capture_s / max(self.attempts, 1):.0f} ms"
        )
        motion = "simulated motion" if self.motion_sim_s else "arm motion"
        out.append(f"{motion} {self.motion_s_per_pick:.2f} s per pick")
        return out


def counts_from_log(events: list[dict[str, Any]]) -> Counts:
    """The summary's counts, recomputed from the log's pick events alone."""
    c = dict.fromkeys(COUNT_KEYS, 0)
    picked: dict[str, int] = {}
    for e in events:
        kind = e["kind"]
        if kind == "target":
            c["attempts"] += 1
            c["retries"] += e["attempt"] > 1
        elif kind == "verify":
            if e["result"] == "picked":
                picked[e["cls"]] = picked.get(e["cls"], 0) + 1
            elif e["result"] == "missed":
                c["misses"] += 1
            elif e["result"] == "rehearsed":
                c["rehearsed"] += 1
        elif kind == "failed":
            c["failed"] += 1
        elif kind == "unreachable":
            c["unreachable"] += 1
    frames = [e for e in events if e["kind"] == "frame"]
    if frames:
        c["unknown_left"] = sum(1 for d in frames[-1]["detections"] if not d["pick"])
    return {**c, "picked": picked}
