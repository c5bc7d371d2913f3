"""Learning-based motion magnification (Oh et al. 2018): network, synthetic data, trainer, magnifier."""
from __future__ import annotations

from odsplat.processing.learned.magnifier import DEFAULT_WEIGHTS, MODES, LearnedMagnifier
from odsplat.processing.learned.network import SIZES, MagNet, from_net, load_magnet, to_net
from odsplat.processing.learned.synth import SynthConfig, SynthSample, make_batch, make_sample
from odsplat.processing.learned.train import TrainConfig, TrainReport, train

__all__ = ["DEFAULT_WEIGHTS", "MODES", "SIZES", "LearnedMagnifier", "MagNet", "SynthConfig", "SynthSample",
           "TrainConfig", "TrainReport", "from_net", "load_magnet", "make_batch", "make_sample", "to_net", "train"]
