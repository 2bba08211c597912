"""Presets and the seam from the command line to the loop: every default lives in TrainConfig or a
preset, the CLI's options are made from the config's fields (and agree with the library), the
fields' types say what they are and are checked."""

import argparse
from dataclasses import fields, replace

import pytest

from course_lib.nerf import cli_nerf
from course_lib.nerf.presets import (FINE_SAMPLES, PRESETS, FractionOfRun, TrainConfig, auto_batch_rays, field_docs,
                                     preset, resolve)
from course_lib.validate import KitInputError


def parse(*argv):
    p = argparse.ArgumentParser()
    cli_nerf.add_arguments(p)
    return p.parse_args(["train", "--out", "x", *argv])


class TestTrainConfig:
    def test_every_field_has_a_section_and_a_docstring(self):
        docs = field_docs()
        assert set(docs) == {f.name for f in fields(TrainConfig)}
        missing = [name for name, (section, doc) in docs.items() if not doc or (name != "preset" and not section)]
        assert missing == []
        assert docs["shrink_box_at"][0] == "voxel grid" and docs["minutes"][0] == "budget and outputs"

    def test_fractions_of_the_run_are_typed_and_checked(self):
        import typing

        hints = typing.get_type_hints(TrainConfig, include_extras=True)
        fractions = {name for name, hint in hints.items() if hint is FractionOfRun}
        assert {"shrink_box_at", "grid_sh_start", "occupancy_start"} <= fractions
        assert isinstance(PRESETS["fast"].shrink_box_at, float)
        with pytest.raises(KitInputError, match="grid_sh_start = 1500: expected a fraction of the run"):
            resolve(preset("fast", grid_sh_start=1500), 100, 100)
        with pytest.raises(KitInputError, match="model = 'mlp': expected one of 'nerf', 'grid'"):
            resolve(preset("fast", model="mlp"), 100, 100)
        with pytest.raises(KitInputError, match="unknown TrainConfig fields"):
            preset("fast", n_sample=3)

    def test_defaults_live_in_the_config(self):
        # a library call without minutes runs the same 5 minutes as the command line
        for name in PRESETS:
            assert preset(name).minutes == 5.0 and preset(name).threads == -1
        assert resolve(preset("fast", minutes=0), 100, 100).minutes is None  # 0: no time limit
        # fine is the paper's fine network with its 128 samples, unless n_importance says otherwise
        assert resolve(preset("paper", fine=True), 100, 100).n_importance == FINE_SAMPLES
        assert resolve(preset("paper", fine=True, n_importance=32), 100, 100).n_importance == 32
        assert resolve(preset("paper"), 100, 100).n_importance == 0

    def test_the_grid_batch_grows_with_the_grid(self):
        # batch_rays = 0: from the grid's resolution, a multiple of 1024, at least 2048; the MLP keeps 1024
        sizes = [resolve(preset("fast", minutes=m), H, H) for H, m in ((100, 5), (200, 5), (400, 5), (800, 10))]
        batches = [c.batch_rays for c in sizes]
        assert batches == sorted(batches) and batches[0] == 2048 and batches[-1] > batches[0]
        assert all(b % 1024 == 0 for b in batches)
        assert auto_batch_rays(sizes[-1].grid_resolution) == batches[-1]
        assert resolve(preset("fast", batch_rays=512), 800, 800).batch_rays == 512  # a number given is kept
        assert resolve(preset("paper"), 800, 800).batch_rays == 1024
        assert resolve(preset("fast", batch_rays=0, model="nerf"), 100, 100).batch_rays == 1024
        with pytest.raises(KitInputError, match="batch_rays = -1: expected a number of rays"):
            resolve(preset("fast", batch_rays=-1), 100, 100)

    def test_round_trip_through_a_dict(self):
        cfg = preset("fast", grid_schedule=((0.0, 0.5), (0.5, 1.0)))
        assert TrainConfig.from_dict(cfg.to_dict()) == cfg


class TestCommandLine:
    def test_one_option_per_field(self):
        p = argparse.ArgumentParser()
        cli_nerf.add_arguments(p)
        train = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction)).choices["train"]
        options = {opt for a in train._actions for opt in a.option_strings}
        for f in fields(TrainConfig):
            if f.name not in cli_nerf.NOT_OPTIONS:
                assert "--" + f.name.replace("_", "-") in options, f.name
        assert {"--batch", "--samples", "--importance", "--sparse-adam", "--black-background", "--no-fine"} <= options

    @pytest.mark.parametrize("name", sorted(PRESETS))
    def test_no_options_is_the_preset(self, name):
        assert cli_nerf.config_from_args(parse("--preset", name)) == preset(name)

    def test_options_set_fields(self):
        cfg = cli_nerf.config_from_args(parse("--preset", "paper", "--fine", "--samples", "32", "--minutes", "1.5",
                                         "--black-background", "--grid-schedule", "((0, 0.5), (0.2, 1.0))",
                                         "--near", "none", "--density", "softplus", "--no-perturb"))
        assert cfg == replace(preset("paper"), fine=True, n_samples=32, minutes=1.5, white_background=False,
                              grid_schedule=((0, 0.5), (0.2, 1.0)), near=None, density="softplus", perturb=False)
        assert resolve(cfg, 100, 100).n_importance == FINE_SAMPLES

    def test_bad_values_are_refused(self, capsys):
        with pytest.raises(SystemExit):
            parse("--density", "tanh")
        assert "invalid choice: 'tanh'" in capsys.readouterr().err
        with pytest.raises(SystemExit):
            parse("--grid-schedule", "(0, 0.5")
        assert "is not a Python literal" in capsys.readouterr().err

    def test_help_comes_from_the_docstrings(self, capsys, monkeypatch):
        monkeypatch.setenv("COLUMNS", "2000")  # one line per option
        with pytest.raises(SystemExit):
            parse("--help")
        out = capsys.readouterr().out
        assert "From when the colour grid holds spherical harmonics" in out and "(paper: 0.0; fast: 0.45)" in out
        assert ":class:" not in out and "``" not in out
