"""What a suspect config.yml may build (config_check.py): the census of installed methods, kept in the cache folder
for the environment it was taken in, refuses what it refused when taken afresh."""

from __future__ import annotations

import copy
import os

import pytest

from gsticker_plugin import config_check as C


@pytest.fixture
def fresh_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("GSTICKER_CACHE_DIR", str(tmp_path / "cache"))
    C.installed_census.cache_clear()
    yield tmp_path / "cache"
    C.installed_census.cache_clear()


def stock_config():
    from nerfstudio.configs.method_configs import all_methods

    return copy.deepcopy(all_methods["gsticker-nerfacto-small"])


def test_the_kept_census_is_the_census_taken_and_is_read_without_importing_the_methods(fresh_cache, monkeypatch):
    taken = C.installed_census()
    assert taken == C.take_census()
    (kept,) = fresh_cache.glob("census-*.json")
    assert kept.name == f"census-{C.census_fingerprint()}.json"
    C.installed_census.cache_clear()

    def no_census():
        raise AssertionError("the census was taken again")

    monkeypatch.setattr(C, "take_census", no_census)
    assert C.installed_census() == taken
    assert C.refusal(stock_config()) is None


@pytest.mark.parametrize("target", [os.system, "lambda"])
def test_code_that_no_method_puts_there_is_refused_with_the_census_read_from_the_cache(
    fresh_cache, monkeypatch, target
):
    C.installed_census()
    C.installed_census.cache_clear()
    monkeypatch.setattr(C, "take_census", lambda: pytest.fail("the census was taken again"))
    cfg = stock_config()
    cfg.pipeline.datamanager.dataparser._target = (lambda: 0) if target == "lambda" else target
    why = C.refusal(cfg)
    assert why is not None and "_target names" in why


def test_a_census_of_another_environment_is_not_read(fresh_cache, monkeypatch, tmp_path):
    C.installed_census()
    before = C.census_fingerprint()
    monkeypatch.setenv("NERFSTUDIO_METHOD_CONFIGS", "mine=my_methods:config")
    assert C.census_fingerprint() != before
    monkeypatch.delenv("NERFSTUDIO_METHOD_CONFIGS")
    assert C.census_fingerprint() == before
    # a changed method file (an editable install edited) names another census
    (tmp_path / "my_methods.py").write_text("config = None\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    stamp = C._file_stamp("my_methods")
    (tmp_path / "my_methods.py").write_text("config = None  # edited\n")
    assert C._file_stamp("my_methods") != stamp


def test_a_damaged_census_file_is_taken_again(fresh_cache):
    taken = C.installed_census()
    (kept,) = fresh_cache.glob("census-*.json")
    kept.write_text("{not json")
    C.installed_census.cache_clear()
    assert C.installed_census() == taken
