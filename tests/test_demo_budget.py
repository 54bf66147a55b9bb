"""The demo's training budget: one number of images seen for every method it compares (the
end-to-end demo runs in tests/test_cli.py)."""

from __future__ import annotations

import pytest

from tdof20.errors import TdofError
from tdof20.experiments.demo import DEFAULT_IMAGES, budget_of


def test_the_default_budget_is_images_seen_in_whole_batches():
    # the defaults' 56 training images, batch 4: 840 images = 210 steps, 15 epochs
    assert budget_of(None, None, 56, 4) == {"images": DEFAULT_IMAGES, "steps": 210, "epochs": 15, "batch": 4}
    assert budget_of(5, None, 56, 4) == {"images": 280, "steps": 70, "epochs": 5, "batch": 4}
    # a budget that ends inside an epoch: the last epoch is cut short, the images are whole batches
    assert budget_of(None, 100, 56, 4) == {"images": 100, "steps": 25, "epochs": 2, "batch": 4}
    assert budget_of(None, 10, 3, 4) == {"images": 12, "steps": 4, "epochs": 4, "batch": 3}


@pytest.mark.parametrize("epochs,images,needle", [
    ({"hff6dof": 5, "pvnet": 15}, None, "one number >= 1 for every method"),
    (0, None, "training epochs must be one number >= 1"),
    (None, 0, "training images must be one number >= 1"),
    (3, 100, "as epochs or as images, not both"),
])
def test_an_unequal_or_empty_budget_is_refused(epochs, images, needle):
    with pytest.raises(TdofError, match=needle):
        budget_of(epochs, images, 56, 4)
