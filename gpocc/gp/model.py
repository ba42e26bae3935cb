"""A trained occupancy model and its self-contained file format.

The model file is a compressed ``.npz`` holding the training samples (means,
covariances, pose factors, labels, scan ids) and one JSON document with the format
version, hyperparameters, classifier, thresholds, the job's config and the versions of
the software that wrote it. It never needs pickle.
"""

from __future__ import annotations

import dataclasses
import json
import platform
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy

import gpocc
from gpocc.blas import single_threaded_blas
from gpocc.config import Config, config_from_dict, config_to_dict
from gpocc.errors import GpoccError
from gpocc.gp.classify import PlattClassifier, fit_classifier
from gpocc.gp.kernels import make_kernel
from gpocc.gp.train import TrainingResult, learn_hyperparameters, make_patches
from gpocc.io.atomic import atomic_path
from gpocc.samples.sampleset import SampleSet

FORMAT_NAME = "gpocc-model"
FORMAT_VERSION = 1
_ARRAYS = ("means", "covariances", "labels", "scan_ids", "pose_factors", "sensor_ids")


@dataclass(frozen=True)
class GPModel:
    """Everything ``gpocc map`` needs: samples, kernel, noise, classifier, settings.

    ``samples`` are the samples the model predicts from: with ``input_noise`` off their
    covariances are zero (the baseline GP), so prediction code needs no switch.
    """

    kernel: Any
    noise_variance: float
    classifier: PlattClassifier
    samples: SampleSet
    config: Config
    input_noise: bool
    training: dict[str, Any] = field(default_factory=dict)
    inputs: tuple[str, ...] = ()

    @property
    def level(self) -> int:
        return self.config.model.quadrature_level

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the sample means, metres."""
        lo = self.samples.means.min(axis=0)
        hi = self.samples.means.max(axis=0)
        return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


def kernel_parameters(kernel: Any) -> dict[str, Any]:
    """The kernel's hyperparameters as plain data (name plus fields)."""
    values = {k: (list(v) if isinstance(v, tuple) else v)
              for k, v in dataclasses.asdict(kernel).items()}
    return {"class": type(kernel).__name__, **values}


def build_model(
    samples: SampleSet, config: Config, inputs: tuple[str, ...] = (),
    on_evaluation: Callable[[int], None] | None = None,
) -> GPModel:
    """Learn hyperparameters and the classifier from ``samples`` under ``config``.

    ``on_evaluation(1)`` is called after each likelihood evaluation (progress display).
    """
    model_cfg = config.model
    if not model_cfg.input_noise:
        samples = samples.without_input_noise()
    kernel = make_kernel(model_cfg.kernel, model_cfg.hyperparameters)
    with single_threaded_blas():
        result: TrainingResult = learn_hyperparameters(
            kernel, model_cfg.hyperparameters.noise_variance, samples,
            model_cfg.quadrature_level, model_cfg.training, config.seed, on_evaluation,
        )
        # Fresh patches (another seed) for the classifier: a and b fitted on the very
        # neighbourhoods whose likelihood chose the hyperparameters would be optimistic.
        patches = make_patches(samples, model_cfg.training, config.seed + 1)
        classifier = fit_classifier(result.kernel, result.noise_variance, patches,
                                    model_cfg.quadrature_level,
                                    model_cfg.training.classifier_holdout)
    training = {
        "log_marginal_likelihood": result.log_marginal_likelihood,
        "initial_log_marginal_likelihood": result.initial_log_marginal_likelihood,
        "evaluations": result.evaluations,
        "patches": list(result.patches),
    }
    return GPModel(
        kernel=result.kernel, noise_variance=result.noise_variance, classifier=classifier,
        samples=samples, config=config, input_noise=model_cfg.input_noise,
        training=training, inputs=tuple(inputs),
    )


def save_model(model: GPModel, path: str | Path) -> None:
    """Write ``model`` to ``path`` (.npz) atomically."""
    meta = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "versions": {"gpocc": gpocc.__version__, "numpy": np.__version__,
                     "scipy": scipy.__version__, "python": platform.python_version()},
        "kernel": kernel_parameters(model.kernel),
        "kernel_name": model.config.model.kernel,
        "noise_variance": model.noise_variance,
        "classifier": {"a": model.classifier.a, "b": model.classifier.b},
        "input_noise": model.input_noise,
        "training": model.training,
        "inputs": list(model.inputs),
        "config": config_to_dict(model.config),
    }
    arrays = {name: getattr(model.samples, name) for name in _ARRAYS}
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, metadata=np.frombuffer(json.dumps(meta).encode(), np.uint8),
                                **arrays)


def load_model(path: str | Path) -> GPModel:
    """Read a model file; a missing, corrupt or newer-format file is a GpoccError."""
    p = Path(path)
    if not p.is_file():
        raise GpoccError(f"{p}: model file not found; create one with `gpocc train`")
    try:
        with np.load(p, allow_pickle=False) as data:
            meta = json.loads(bytes(data["metadata"]).decode())
            arrays = {name: data[name] for name in _ARRAYS}
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, json.JSONDecodeError,
            EOFError, UnicodeDecodeError):
        raise GpoccError(f"{p}: not a gpocc model file or corrupt; re-create it with "
                         "`gpocc train`") from None
    if meta.get("format") != FORMAT_NAME:
        raise GpoccError(f"{p}: not a gpocc model file; re-create it with `gpocc train`")
    version = meta.get("format_version")
    if not isinstance(version, int) or version > FORMAT_VERSION:
        raise GpoccError(
            f"{p}: model format version {version} is newer than this gpocc understands "
            f"({FORMAT_VERSION}); upgrade gpocc or re-train with this version"
        )
    config = config_from_dict(meta["config"], f"{p} (embedded config)")
    params = {k: (tuple(v) if isinstance(v, list) else v)
              for k, v in meta["kernel"].items() if k != "class"}
    kernel_cls = type(make_kernel(meta["kernel_name"], config.model.hyperparameters))
    kernel = kernel_cls(**params)
    return GPModel(
        kernel=kernel,
        noise_variance=float(meta["noise_variance"]),
        classifier=PlattClassifier(**meta["classifier"]),
        samples=SampleSet(**arrays),
        config=config,
        input_noise=bool(meta["input_noise"]),
        training=meta.get("training", {}),
        inputs=tuple(meta.get("inputs", ())),
    )
