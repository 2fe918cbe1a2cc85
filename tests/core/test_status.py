"""The sentences of a sensor's notes and warnings (:mod:`imucal_cli.core.status`)."""

from __future__ import annotations

import numpy as np

from imucal_cli.core.status import own_error_sentences


def test_an_error_group_names_only_the_components_the_drive_determined():
    """A triad's axis errors of which the drive determined the x scale and one angle: the
    others are held at zero, and the note says so (``-``) rather than print them as found."""
    nan = float("nan")
    group = {
        "estimated": True,
        "value": np.array([0.01, 0.0, 0.0, np.radians(0.5), 0.0, 0.0]),
        "std": np.array([0.001, nan, nan, 0.001, nan, nan]),
        "chi2": 30.0,
        "dof": 2,
    }
    (sentence,) = own_error_sentences({"base gyro": group})
    assert sentence.startswith("base gyro axis errors estimated with the extrinsics: ")
    assert "scale +1.00%, -, -; non-orthogonality +0.500, -, - deg (chi2 30, 2 dof)" in sentence
    group["std"] = np.array([nan, nan, nan, 0.001, 0.001, 0.001])
    (sentence,) = own_error_sentences({"base gyro": group})
    assert "scale" not in sentence and "non-orthogonality +0.500, +0.000, +0.000 deg" in sentence
    assert own_error_sentences({"base gyro": {"estimated": False}}) == []
