"""data.process.retrieval: image pairs chosen by a vocabulary of the capture's own SIFT descriptors.

Synthetic descriptors are uint8 blobs (a centre plus small noise). The "images" of the retrieval
tests lie on a ring: image i draws from blobs 2i-2 .. 2i+2 (of 2n), so it shares three blobs with
i - 1 and i + 1, one with i - 2 and i + 2, none with the rest.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from exploregs_plugin.data.process import retrieval
from exploregs_plugin.data.process.retrieval import (
    assign_words,
    build_vocabulary,
    capture_is_ordered,
    more_pairs,
    nearest_words,
    plan_pairs,
    ranked_neighbours,
    read_descriptors,
    retrieval_pairs,
    similarity,
    tfidf_vectors,
)

N_RING = 30


def blobs(count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` blob centres, far apart: random in [20, 235]^128, so about 1000 apart against a
    noise of +-3 per value."""
    return rng.integers(20, 236, (count, 128))


def draw(centres: np.ndarray, which: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Descriptors near ``centres[which]`` (uint8, noise in [-3, 3])."""
    return np.clip(centres[which] + rng.integers(-3, 4, (len(which), 128)), 0, 255).astype(np.uint8)


def ring_images(n: int = N_RING, per_blob: int = 20, seed: int = 0) -> list[np.ndarray]:
    """Descriptors of ``n`` images on a ring (module docstring)."""
    rng = np.random.default_rng(seed)
    centres = blobs(2 * n, rng)
    return [draw(centres, np.repeat(np.arange(2 * i - 2, 2 * i + 3) % (2 * n), per_blob), rng) for i in range(n)]


def ring_similarity(n: int = N_RING) -> np.ndarray:
    images = ring_images(n)
    vocabulary = build_vocabulary(images, 2 * n)
    return similarity(tfidf_vectors(assign_words(images, vocabulary), len(vocabulary)))


def ring_names(n: int = N_RING) -> list[str]:
    """Names whose list order is not their alphabetical order: "earlier" must mean earlier in the list."""
    return [f"view_{n - i:03d}.jpg" for i in range(n)]


# --- vocabulary -----------------------------------------------------------------------------------


def test_kmeans_recovers_well_separated_blobs_with_integer_centroids():
    rng = np.random.default_rng(3)
    centres = blobs(8, rng)
    which = np.repeat(np.arange(8), 60)
    points = draw(centres, which, rng)
    images = [points[i::5] for i in range(5)]  # spread over images, as descriptors are
    vocabulary = build_vocabulary(images, words=8)
    assert vocabulary.shape == (8, 128) and vocabulary.dtype == np.float32
    assert np.array_equal(vocabulary, np.rint(vocabulary))
    labels = np.concatenate(assign_words(images, vocabulary))
    blob_of = np.concatenate([which[i::5] for i in range(5)])
    word_of_blob = [np.unique(labels[blob_of == b]) for b in range(8)]
    assert all(len(w) == 1 for w in word_of_blob), "a blob split over several words"
    assert len({int(w[0]) for w in word_of_blob}) == 8, "two blobs share a word"
    # each word is its blob's centre to within the noise
    for b, w in enumerate(word_of_blob):
        assert np.abs(vocabulary[w[0]] - centres[b]).max() <= 3


def test_nearest_words_are_exact_and_ties_go_to_the_lower_index(monkeypatch):
    rng = np.random.default_rng(0)
    x = rng.integers(0, 256, (500, 128)).astype(np.uint8)
    x[:3] = np.array([[0], [255], [128]])  # extreme rows: the largest distances
    vocabulary = rng.integers(0, 256, (40, 128)).astype(np.float32)
    vocabulary[7] = 255.0
    vocabulary[30] = vocabulary[12]  # a duplicate word: every tie must go to 12
    labels, dist = nearest_words(x, vocabulary)
    exact = ((x[:, None, :].astype(np.int64) - vocabulary[None].astype(np.int64)) ** 2).sum(-1)
    assert np.array_equal(labels, exact.argmin(1))
    assert np.array_equal(dist, exact.min(1))
    assert not np.any(labels == 30) and np.any(labels == 12)
    # another summation order (columns permuted) and other BLAS shapes (tiny chunks): same bits
    perm = rng.permutation(128)
    monkeypatch.setattr(retrieval, "CHUNK_BYTES", 4 * 40 * 7)
    again = nearest_words(np.ascontiguousarray(x[:, perm]), np.ascontiguousarray(vocabulary[:, perm]))
    assert np.array_equal(again[0], labels) and np.array_equal(again[1], dist)
    with pytest.raises(ValueError, match="integers"):
        nearest_words(x, vocabulary + 0.5)


def test_vocabulary_is_reproducible_and_its_seed_matters():
    images = ring_images(12, per_blob=10)
    first = build_vocabulary(images, 16, sample=500, seed=0)
    assert np.array_equal(first, build_vocabulary(images, 16, sample=500, seed=0))
    assert not np.array_equal(first, build_vocabulary(images, 16, sample=500, seed=1))


def test_fewer_distinct_descriptors_than_words_give_fewer_words():
    rng = np.random.default_rng(0)
    rows = rng.integers(0, 256, (5, 128)).astype(np.uint8)
    images = [rows[[0, 1, 1, 2]], rows[[2, 3, 4, 4]], np.zeros((0, 128), np.uint8)]
    vocabulary = build_vocabulary(images, 50)
    assert sorted(map(bytes, vocabulary.astype(np.uint8))) == sorted(map(bytes, rows))
    with pytest.raises(ValueError, match="no descriptors"):
        build_vocabulary([np.zeros((0, 128), np.uint8)], 4)
    with pytest.raises(ValueError, match="one word"):
        build_vocabulary(images, 0)


THREADS_SCRIPT = """
import hashlib, importlib.util, sys
import numpy as np
spec = importlib.util.spec_from_file_location("retrieval", sys.argv[1])
r = importlib.util.module_from_spec(spec)
spec.loader.exec_module(r)
rng = np.random.default_rng(5)
centres = rng.integers(0, 200, (300, 128))
images = [np.clip(centres[rng.integers(0, 300, 600)] + rng.integers(-40, 41, (600, 128)), 0, 255).astype(np.uint8)
          for _ in range(40)]
vocabulary = r.build_vocabulary(images, 256, iterations=4, sample=20000)
words = r.assign_words(images, vocabulary)
sim = r.similarity(r.tfidf_vectors(words, len(vocabulary)))
h = hashlib.sha256(vocabulary.tobytes())
for w in words:
    h.update(w.tobytes())
h.update(sim.tobytes())
print(h.hexdigest())
"""


def test_vocabulary_words_and_similarity_are_the_same_bits_on_one_and_two_threads():
    # threadpoolctl is not a dependency: BLAS reads its thread count from the environment at start,
    # so each count runs in its own process (the module loaded from its file: no torch import)
    digests = []
    for threads in ("1", "2"):
        env = dict(os.environ, OPENBLAS_NUM_THREADS=threads, OMP_NUM_THREADS=threads, MKL_NUM_THREADS=threads)
        out = subprocess.run([sys.executable, "-c", THREADS_SCRIPT, retrieval.__file__], check=False,
                             env=env, capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        digests.append(out.stdout.strip())
    assert len(digests[0]) == 64 and digests[0] == digests[1]


# --- TF-IDF and similarity ------------------------------------------------------------------------


def test_tfidf_ignores_words_in_every_image_and_rows_are_unit_or_zero():
    words = [np.array([0, 0, 1, 2]), np.array([0, 2, 2]), np.array([0, 3]), np.array([], np.int64)]
    v = tfidf_vectors(words, 5)
    assert v.shape == (4, 5) and np.isfinite(v).all()
    # word 0 is in every image that has words, but the empty image counts in N: idf = log(4/3)
    assert np.allclose(np.linalg.norm(v[:3], axis=1), 1.0)
    assert np.array_equal(v[3], np.zeros(5))
    assert np.array_equal(v[:, 4], np.zeros(4))  # a word no image has
    expected = np.array([2 / 4 * np.log(4 / 3), 1 / 4 * np.log(4), 1 / 4 * np.log(2), 0.0, 0.0])
    assert np.allclose(v[0], expected / np.linalg.norm(expected))
    # a word in every image has idf log(N / N) = 0: adding it changes no vector's direction
    everywhere = tfidf_vectors([np.append(w, 4) for w in words[:3]], 5)
    assert np.array_equal(everywhere[:, 4], np.zeros(3))
    assert np.allclose(everywhere, tfidf_vectors(words[:3], 5))
    with pytest.raises(ValueError, match="outside"):
        tfidf_vectors([np.array([5])], 5)


def test_similarity_is_the_cosine_with_minus_infinity_on_the_diagonal():
    rng = np.random.default_rng(0)
    v = rng.random((6, 50)) * (rng.random((6, 50)) < 0.3)
    v[5] = 0.0
    sim = similarity(v)
    u = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)
    off = ~np.eye(6, dtype=bool)
    assert np.abs(sim - u @ u.T)[off].max() < 1e-5
    assert np.all(np.isneginf(np.diag(sim)))
    assert np.array_equal(sim, sim.T)
    assert np.array_equal(sim[5][off[5]], np.zeros(5))
    # exact products of integer vectors: similarities are multiples of 2^-40
    q = sim[off] * float(retrieval.QUANTUM) ** 2
    assert np.array_equal(q, np.rint(q))


# --- retrieval on the ring ------------------------------------------------------------------------


def test_ring_neighbours_are_the_most_similar_and_the_order_is_recognised():
    sim = ring_similarity()
    n = N_RING
    top2 = ranked_neighbours(sim, 2)
    assert all(set(top2[i].tolist()) == {(i - 1) % n, (i + 1) % n} for i in range(n))
    assert capture_is_ordered(sim, top_k=2)
    perm = np.random.default_rng(0).permutation(n)
    assert not capture_is_ordered(sim[np.ix_(perm, perm)], top_k=2)
    # the top-k never holds the image itself, however large k is
    assert all(i not in row for i, row in enumerate(ranked_neighbours(sim, 100).tolist()))
    assert ranked_neighbours(sim, 100).shape == (n, n - 1)


def test_equal_similarities_rank_in_index_order():
    v = np.zeros((40, 8))
    v[[3, 17, 25], 0] = 1.0  # three equal images; the other 37 empty: similarity 0 to all
    ranked = ranked_neighbours(similarity(v), 39)
    assert ranked[17].tolist() == [3, 25] + [j for j in range(40) if j not in (3, 17, 25)]
    assert ranked[0].tolist() == [j for j in range(1, 40)]


def test_retrieval_pairs_are_unique_earlier_first_and_sequential_only_as_asked():
    sim = ring_similarity()
    names = ring_names()
    n = N_RING
    position = {name: i for i, name in enumerate(names)}
    ring = {(i, i + 1) for i in range(n - 1)} | {(0, n - 1)}
    pairs = retrieval_pairs(names, sim, top_k=2, sequential_overlap=0)
    as_index = [(position[a], position[b]) for a, b in pairs]
    assert as_index == sorted(set(as_index)) and all(a < b for a, b in as_index)
    assert set(as_index) == ring
    with_seq = retrieval_pairs(names, sim, top_k=2, sequential_overlap=3)
    as_index = [(position[a], position[b]) for a, b in with_seq]
    assert as_index == sorted(set(as_index))
    assert set(as_index) == ring | {(i, j) for i in range(n) for j in range(i + 1, min(n, i + 4))}
    assert len(with_seq) < n * (n - 1) / 2 / 4
    with pytest.raises(ValueError, match="names"):
        retrieval_pairs(names[:-1], sim, 2, 0)


def test_more_pairs_leave_out_the_pairs_already_matched():
    sim = ring_similarity()
    names = ring_names()
    done = {frozenset((names[4], names[5])), frozenset((names[5], names[7]))}
    pairs = more_pairs(names, sim, [names[5], names[6]], top_k=4, done=done)
    position = {name: i for i, name in enumerate(names)}
    as_index = [(position[a], position[b]) for a, b in pairs]
    # 5's four nearest are 4, 6 (three shared blobs) and 3, 7 (one); 6's are 5, 7, 4, 8
    assert as_index == [(3, 5), (4, 6), (5, 6), (6, 7), (6, 8)]
    assert not {frozenset(p) for p in pairs} & done
    with pytest.raises(KeyError):
        more_pairs(names, sim, ["not_a_photo.jpg"], 4, set())


# --- the COLMAP database --------------------------------------------------------------------------


def write_database(path: Path, descriptors: dict[str, np.ndarray]) -> None:
    """A COLMAP database with one camera and an image per name, with its descriptors (none for an
    empty array)."""
    with pycolmap.Database.open(path) as db:
        camera_id = db.write_camera(pycolmap.Camera.create_from_model_name(1, "SIMPLE_PINHOLE", 100.0, 64, 48))
        for name, d in descriptors.items():
            image_id = db.write_image(pycolmap.Image(name=name, camera_id=camera_id))
            if len(d):
                sift = pycolmap.FeatureDescriptors(type=pycolmap.FeatureExtractorType.SIFT, data=d)
                db.write_descriptors(image_id, sift)


def test_read_descriptors_takes_a_seeded_subset_of_the_stored_rows(tmp_path):
    rng = np.random.default_rng(0)
    stored = {"a.jpg": rng.integers(0, 256, (50, 128)).astype(np.uint8),
              "b.jpg": np.zeros((0, 128), np.uint8),
              "c.jpg": rng.integers(0, 256, (10, 128)).astype(np.uint8)}
    stored["a.jpg"][:, 0] = np.arange(50)  # each row tells its index
    database = tmp_path / "database.db"
    write_database(database, stored)
    names = ["a.jpg", "b.jpg", "c.jpg"]
    a, b, c = read_descriptors(database, names, per_image=20)
    assert a.shape == (20, 128) and a.dtype == np.uint8
    rows = a[:, 0].astype(int)
    assert np.all(np.diff(rows) > 0)  # distinct rows, in stored order
    assert np.array_equal(a, stored["a.jpg"][rows])
    assert b.shape == (0, 128) and b.dtype == np.uint8
    assert np.array_equal(c, stored["c.jpg"])  # fewer than per_image: all of them
    again = read_descriptors(database, names, per_image=20)
    assert all(np.array_equal(x, y) for x, y in zip((a, b, c), again))
    assert not np.array_equal(read_descriptors(database, names, per_image=20, seed=1)[0], a)
    with pytest.raises(KeyError, match="d.jpg"):
        read_descriptors(database, ["d.jpg"], per_image=20)


def test_plan_pairs_from_a_database(tmp_path):
    names = ring_names()
    database = tmp_path / "database.db"
    write_database(database, dict(zip(names, ring_images())))
    plan = plan_pairs(database, names, top_k=2, words=2 * N_RING, sequential_overlap=2)
    assert plan.ordered and plan.sim.shape == (N_RING, N_RING)
    position = {name: i for i, name in enumerate(names)}
    ring = {(i, i + 1) for i in range(N_RING - 1)} | {(0, N_RING - 1)}
    assert {(position[a], position[b]) for a, b in plan.pairs} == ring | {(i, i + 2) for i in range(N_RING - 2)}
    # shuffled names: the order is no capture order, so no sequential pairs
    shuffled = [names[i] for i in np.random.default_rng(0).permutation(N_RING)]
    plan = plan_pairs(database, shuffled, top_k=2, words=2 * N_RING, sequential_overlap=2)
    assert not plan.ordered
    assert {frozenset(p) for p in plan.pairs} == {frozenset((names[a], names[b])) for a, b in ring}
