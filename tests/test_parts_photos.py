"""Real front-lit photos nobody here drew (../shared/data/parts-photos, labels.csv)."""

from __future__ import annotations

import csv

import cv2
import pytest

from cell.vision.config import PartsConfig
from cell.vision.locate import locate
from tests.helpers import DATA, need

PHOTOS = DATA / "parts-photos"
MM_PER_PX = 0.3  # about right for these photos (a nut is some 40 px across flats)

# What each photo must give, from labels.csv's descriptions: the sorted classes found, and
# for the hard cases which class a part must never get.
EXPECTED = {
    "packt_nut_tuerca_0000.png": ["nut"],
    "packt_nut_tuerca_0003.png": ["nut", "nut"],
    "packt_nut_tuerca_0020.png": ["nut"],
    "packt_nut_tuerca_0040.png": ["nut"],
    "packt_nut_tuerca_0060.png": ["nut"],
    "packt_nut_tuerca_0080.png": ["nut"],
    "packt_nut_tuerca_0100.png": ["nut"],
    "packt_nut_tuerca_0120.png": ["nut"],
    "packt_nut_tuerca_0140.png": ["nut"],
    "packt_nut_tuerca_0150.png": ["unknown"],  # on its side: never a bolt (nor a flat nut)
    "packt_screw_tornillo_0000.png": ["bolt"],
    "packt_screw_tornillo_0020.png": ["unknown"],  # cut by the border: never picked
    "packt_screw_tornillo_0040.png": ["bolt"],
    "packt_screw_tornillo_0060.png": ["bolt"],
    "packt_screw_tornillo_0080.png": ["bolt"],
    "packt_screw_tornillo_0100.png": ["unknown"],  # standing on its head: never a nut
    "packt_screw_tornillo_0120.png": ["bolt"],
    "packt_screw_tornillo_0140.png": ["bolt"],
    "packt_screw_tornillo_0025.png": ["bolt", "unknown"],
    "packt_screw_tornillo_0002.png": ["bolt", "unknown"],
    "packt_ring_arandela_0000.png": ["unknown", "unknown"],
    "packt_ring_arandela_0030.png": ["unknown"],
    "packt_ring_arandela_0070.png": ["unknown"],
    "packt_ring_arandela_0100.png": ["unknown"],
    "packt_scene_ch05_test.png": ["bolt", "nut", "unknown", "unknown"],
    "packt_background_ch06_pattern.png": [],
    "packt_background_ch05_light.png": [],
}


def _labels() -> dict[str, dict]:
    with open(need(PHOTOS / "labels.csv"), newline="", encoding="utf-8") as f:
        return {row["file"]: row for row in csv.DictReader(f)}


def test_every_labelled_photo_has_an_expectation():
    assert set(_labels()) == set(EXPECTED)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_photo(name):
    row = _labels()[name]
    image = cv2.imread(str(need(PHOTOS / name)), cv2.IMREAD_COLOR)
    result = locate(image, MM_PER_PX, PartsConfig())
    got = sorted(o.cls for o in result.objects)
    assert got == EXPECTED[name], [(o.cls, o.reason) for o in result.objects]
    # The labels' object counts agree with what was found.
    count = 0 if row["objects"] == "0" else sum(int(t.split()[0]) for t in row["objects"].split("+"))
    assert len(result.objects) == count
    for o in result.objects:
        assert o.pick == (o.cls in ("nut", "bolt"))
        if "standing" in row["description"] and o.cls != "bolt":
            assert o.cls != "nut"
    if "CLIPPED" in row["description"]:
        assert not any(o.pick for o in result.objects)
        assert any("border" in o.reason for o in result.objects)


def test_hard_cases_say_why():
    reasons = {
        name: [o.reason for o in locate(cv2.imread(str(need(PHOTOS / name))), MM_PER_PX).objects]
        for name in ("packt_nut_tuerca_0150.png", "packt_screw_tornillo_0100.png", "packt_ring_arandela_0030.png")
    }
    assert "on its side" in reasons["packt_nut_tuerca_0150.png"][0]
    assert "standing on its head" in reasons["packt_screw_tornillo_0100.png"][0]
    assert "washer" in reasons["packt_ring_arandela_0030.png"][0]
