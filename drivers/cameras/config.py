"""Camera configuration: where frames come from, validated like the rest of the cell's TOML."""

from __future__ import annotations

from pydantic import Field

from drivers.config import Strict


class CameraConfig(Strict):
    """Where frames come from."""

    source: str = Field("sim", description="'sim', a device index, a URL, a video file or an image folder")
    width_px: int = Field(1920, ge=16, le=20000)
    height_px: int = Field(1080, ge=16, le=20000)
    timeout_s: float = Field(5.0, gt=0, le=120)
    focus: float | None = Field(
        None, ge=0, description="fixed focus (device units); None: leave as is (autofocus is off)"
    )
    exposure: float | None = Field(None, description="fixed exposure (device units); None: leave auto-exposure on")
    warmup_frames: int = Field(5, ge=0, le=100, description="frames dropped after opening, while exposure settles")
    loop: bool = Field(False, description="video file or image folder: start again at the end")
    max_image_px: int = Field(
        100_000_000, ge=256, description="an image file with more pixels is refused from its header, before decoding"
    )
