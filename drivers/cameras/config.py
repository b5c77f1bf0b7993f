"""Camera configuration: where frames come from, validated like the rest of the cell's TOML."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from drivers.config import Strict

GENICAM_PREFIX = "genicam:"
PixelFormat = Literal["Mono8", "BayerRG8", "BayerGR8", "BayerGB8", "BayerBG8", "RGB8", "BGR8"]
FeatureValue = bool | int | float | str


class GenICamConfig(Strict):
    """A GigE Vision or USB3 Vision camera through Aravis (camera.source = "genicam:<id>";
    docs/cameras.md). Every setting is checked against the camera's own GenICam description when it
    opens; None leaves the camera's own value."""

    exposure_us: float | None = Field(
        None, gt=0, description="exposure time in µs (auto exposure turned off); None: leave the camera's"
    )
    gain_db: float | None = Field(None, ge=0, description="analog gain in dB (auto gain turned off); None: leave it")
    pixel_format: PixelFormat = Field(
        "Mono8", description="the camera's pixel format; Bayer and RGB formats are converted to BGR, Mono8 to grey BGR"
    )
    trigger: Literal["software", "line", "free-run"] = Field(
        "software",
        description="'software': one frame exposed per capture; 'line': a frame per pulse on trigger_line; "
        "'free-run': the camera streams, a capture takes the first frame begun after its request",
    )
    trigger_line: str = Field("Line0", description="with trigger = 'line': the camera's input line (TriggerSource)")
    packet_size_bytes: int | None = Field(
        None,
        ge=576,
        le=16384,
        description="GigE: stream packet size (GevSCPSPacketSize); None: the largest the path carries "
        "(9000 needs jumbo frames on every hop)",
    )
    inter_packet_delay_ns: int = Field(
        0, ge=0, le=1_000_000, description="GigE: pause between stream packets (GevSCPD), for a shared or slow link"
    )
    buffer_count: int = Field(4, ge=2, le=64, description="frame buffers queued to the stream")
    acquisition_timeout_s: float = Field(
        2.0, gt=0, le=60, description="a capture's time for a complete frame, retries of incomplete ones included"
    )
    loss_alarm_percent: float = Field(
        5.0,
        gt=0,
        le=100,
        description="a warning when more than this share of the last loss_window_frames frames came incomplete",
    )
    loss_window_frames: int = Field(100, ge=10, le=10_000, description="the frames loss_alarm_percent is taken over")
    features: dict[str, FeatureValue] = Field(
        default_factory=dict,
        description="any other GenICam feature by name, set in this order after the above "
        '(e.g. { BalanceWhiteAuto = "Off" }); an unknown feature or a value out of range is refused',
    )


class CameraConfig(Strict):
    """Where frames come from."""

    source: str = Field(
        "sim",
        description="'sim', a device index, a URL, a video file, an image folder, or 'genicam:<id>' "
        "(`run-cell cameras` lists them)",
    )
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
    genicam: GenICamConfig = Field(
        default_factory=GenICamConfig, description="a GenICam camera's settings (source = 'genicam:<id>')"
    )
