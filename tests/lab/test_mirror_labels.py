"""lab.mirror_labels: where the classifier's mirror image changes a label, and how far from the
thresholds the classifier alone answered there."""

from __future__ import annotations

import numpy as np

from lab.mirror_labels import main, margins


def test_a_points_margin_is_its_distance_from_the_threshold_that_reads_it():
    answer = np.array([[0.0, 0.0],     # open: 0.75 N s below pressing
                       [1.0, 0.0],     # sticks: 0.25 above pressing, 0.5 inside its friction limit
                       [1.0, 0.45],    # sticks, 0.05 N s short of sliding
                       [0.8, 0.0]])    # presses by 0.05 N s
    mu = np.full(4, 0.5)
    np.testing.assert_allclose(margins(answer, mu, pressing=0.75, share=1.0), [0.75, 0.25, 0.05, 0.05])


def test_it_counts_the_steps_where_the_mirror_changes_a_label(capsys):
    assert main(["--seeds", "850", "--steps", "150"]) == 0
    out = capsys.readouterr().out
    assert "the mirror image changes a label at" in out and "steps whose every point lies farther than 0.3" in out
    assert main(["--seeds", "nine"]) == 2
