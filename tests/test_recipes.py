"""Recipes (cell.recipes) and the results store (cell.service.results)."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import pytest

from cell.config import CellConfig
from cell.recipes import RecipeBook, RecipeError, parse_recipe
from cell.service.results import MemoryResultStore, ResultFilter, VisionResult
from tests.mv_harness import RECIPE_BOLTS, RECIPE_NUTS

pytestmark = pytest.mark.timeout(30)


def test_a_recipe_applies_its_handling_and_vision_limits() -> None:
    recipe = parse_recipe(RECIPE_BOLTS + "\n[parts.bolt]\nlength_mm = [20.0, 40.0]\n", "test")
    assert recipe.classes == {"bolt"} and recipe.products == ["kit-7"]
    cfg = recipe.apply(CellConfig())
    assert cfg.planning.pick_order == "rows"
    assert cfg.planning.bolt.bin_robot_mm == (-200.0, 60.0, 60.0)
    assert cfg.parts.bolt.length_mm == (20.0, 40.0)
    assert cfg.planning.nut == CellConfig().planning.nut, "a class the recipe does not pick keeps the config's plan"


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("pick = [", "not valid TOML"),
        ("description = 'x'\n", "pick: Field required"),
        ("[pick.washer]\npick_above_table_mm = 1\nbin_robot_mm = [0, 0, 0]\n", "pick.washer"),
        (RECIPE_NUTS.replace("2.0", "nan"), "pick.nut.pick_above_table_mm"),
        (RECIPE_NUTS + "speed = 3\n", "speed: Extra inputs are not permitted"),
        (RECIPE_NUTS + "[parts.nut]\nacross_flats_mm = [19.0, 6.5]\n", "parts.nut"),
    ],
)
def test_a_bad_recipe_is_refused_saying_what_and_where(text: str, says: str) -> None:
    with pytest.raises(RecipeError) as err:
        parse_recipe(text, "recipe 'x'")
    assert "recipe 'x'" in str(err.value) and says in str(err.value)


def test_the_book_lists_adds_refuses_and_removes(tmp_path: Path) -> None:
    book = RecipeBook(tmp_path / "recipes")
    assert book.list() == []
    info = book.add("bolts-only", RECIPE_BOLTS)
    assert info.recipe_id == "bolts-only" and len(info.sha256) == 64 and info.products == ("kit-7",)
    assert book.add("bolts-only", RECIPE_BOLTS).sha256 == info.sha256, "the same content again is accepted"
    with pytest.raises(RecipeError, match="already exists"):
        book.add("bolts-only", RECIPE_NUTS)
    with pytest.raises(RecipeError, match="invalid recipe"):
        book.add("broken", RECIPE_NUTS.replace("2.0", "-1.0"))
    assert not (tmp_path / "recipes" / "broken.toml").exists(), "nothing half-written"
    for bad_id in ("../etc", "a b", "", ".hidden"):
        with pytest.raises(RecipeError, match="not allowed"):
            book.add(bad_id, RECIPE_NUTS)
    (tmp_path / "recipes" / "hand-edited.toml").write_text("pick = 3\n")
    listed = {i.recipe_id: i for i in book.list()}
    assert set(listed) == {"bolts-only", "hand-edited"} and listed["hand-edited"].error
    assert book.load("bolts-only").classes == {"bolt"}
    book.remove("bolts-only")
    with pytest.raises(RecipeError, match="not found"):
        book.load("bolts-only")
    with pytest.raises(RecipeError, match="not found"):
        book.remove("bolts-only")


def _result(n: int, job: str = "j1", state: int = 1, meas: str = "") -> VisionResult:
    t = datetime(2026, 1, 1, tzinfo=UTC)
    return VisionResult(f"{job}/{n}", job, "pick", state, t, t, 1.0, False, meas_id=meas)


def test_the_memory_store_keeps_the_newest_and_filters() -> None:
    store = MemoryResultStore(capacity=5)
    for n in range(1, 8):
        store.add(_result(n, state=1 if n % 2 else 4, meas="m" if n > 5 else ""))
    assert store.get("j1/1") is None and store.get("j1/7") is not None, "the oldest were forgotten"
    page, total = store.query(ResultFilter(), 1, 2)
    assert total == 5 and [r.result_id for r in page] == ["j1/4", "j1/5"]
    assert [r.result_id for r in store.query(ResultFilter(result_state=4), 0, 10)[0]] == ["j1/4", "j1/6"]
    assert [r.result_id for r in store.query(ResultFilter(meas_id="m"), 0, 10)[0]] == ["j1/6", "j1/7"]
    assert store.query(ResultFilter(job_id="other"), 0, 10) == ([], 0)
