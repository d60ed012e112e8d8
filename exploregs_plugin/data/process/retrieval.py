"""Image pairs to match chosen by image retrieval, not all pairs.

Exhaustive matching is quadratic (252 photos: 31,626 pairs, 29 minutes). Retrieval pairs each
photo with the few photos that look most like it: each image becomes a TF-IDF weighted bag of
visual words (Sivic & Zisserman 2003, "Video Google"), similarity is the cosine of two such
vectors, and each image is matched with its ``top_k`` most similar images, plus its next few
images in name order when the names are a capture order (a walk, video frames).

The vocabulary (the visual words) is built by k-means from the capture's own SIFT descriptors:
COLMAP's vocabulary-tree files are downloads, and a capture is posed offline. A few hundred photos
of one object or room give 10^5 descriptors and more, enough for a vocabulary of a thousand words.

Every step gives the same bits on any thread count, as the rest of the pipeline does: the
k-means centroids are kept integer-valued, so every distance is an integer below 2^24 that a
float32 matrix product computes exactly in any summation order (see :func:`nearest_words`), and
the similarities are products of integer-quantised vectors, exact in float64 (see
:func:`similarity`). Ties are broken by the lower index everywhere.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
import pycolmap

SIFT_DIM = 128
PER_IMAGE = 1500
"""Descriptors read per image. SIFT gives a few thousand per photo (COLMAP keeps up to 8192); a
random 1500 are a fair sample of the photo's words (on the beer capture below, 500 a frame found
89-92% of the strong pairs where 1500 found 96-98%), and assigning words costs linear in the count
(250 images x 1500 = 375,000 descriptors)."""
SAMPLE = 100_000
"""Descriptors the vocabulary's k-means sees: its cost is sample x words x iterations."""
DESCRIPTORS_PER_WORD = 100
"""A word is the mean of about this many sample descriptors: far fewer and a word is one feature
(the vocabulary is as big as the sample and words stop being shared between images)."""
MAX_WORDS = 1024
"""Most words (a full sample of 100,000 gives 1000). On a 71-frame video capture (beer, 1500
descriptors a frame) 1024 words found 98% of the pairs that verified with >= 100 inliers at
top_k 20, 512 and 2048 words 96%; and k-means costs words x sample x iterations."""
TOP_K = 20
"""Most similar images matched with each image. hloc retrieves 20-50 for large scenes; one object
or room of 100-400 photos is seen by fewer photos per view. On the beer capture top_k 10 / 15 /
20 found 76% / 90% / 98% of the pairs with >= 100 inliers; the pairs stay near n x top_k
(250 photos: about 4,500 with the sequential ones, instead of 31,125)."""
SEQUENTIAL_OVERLAP = 5
"""Next images in name order also matched, when the order is a capture order: neighbouring frames
overlap most, even where they look alike to retrieval (plain walls, repeated texture)."""
CHUNK_BYTES = 8 * 2**20
"""Largest temporary distance matrix (float32 rows x words) built at once: one that stays in the
cache is a third faster than 64 MB (100,000 x 2000 words: 0.29 s against 0.46 s on 2 cores)."""
QUANTUM = 2**20
"""Cosine similarity on vectors rounded to multiples of 1 / QUANTUM (see :func:`similarity`)."""


def _as_sift(descriptors: np.ndarray) -> np.ndarray:
    """``descriptors`` as a uint8 [n, 128] array; an empty array of any shape becomes [0, 128].

    uint8 matters: the exact integer arithmetic relies on values in [0, 255]."""
    d = np.asarray(descriptors)
    if d.size == 0:
        return np.zeros((0, SIFT_DIM), np.uint8)
    if d.dtype != np.uint8 or d.ndim != 2 or d.shape[1] != SIFT_DIM:
        raise ValueError(f"expected uint8 SIFT descriptors [n, {SIFT_DIM}], got {d.dtype} {list(d.shape)}")
    return d


def read_descriptors(database: Path, names: list[str], per_image: int = PER_IMAGE,
                     seed: int = 0) -> list[np.ndarray]:
    """Up to ``per_image`` SIFT descriptors (uint8 [n, 128]) of each image in ``names``, in order,
    from a COLMAP database; an image without features gives [0, 128].

    The subset is drawn without replacement by a generator seeded from ``(seed, i)``, ``i`` the
    image's position in ``names``, and kept in stored order: an image's subset does not depend on
    which images were read before it."""
    out = []
    with pycolmap.Database.open(database) as db:
        for i, name in enumerate(names):
            image = db.read_image_with_name(name)
            if image is None:
                raise KeyError(f"image {name!r} is not in the database {database}")
            stored = db.read_descriptors(image.image_id)
            data = _as_sift(getattr(stored, "data", stored))  # pycolmap 4.2 wraps the array
            if len(data) > per_image:
                rng = np.random.default_rng([seed, i])
                data = data[np.sort(rng.choice(len(data), per_image, replace=False))]
            out.append(np.ascontiguousarray(data))
    return out


def _chunk_rows(words: int) -> int:
    """Rows per chunk so that a float32 [rows, words] distance matrix stays within CHUNK_BYTES."""
    return max(1, CHUNK_BYTES // (4 * max(words, 1)))


def _check_vocabulary(vocabulary: np.ndarray) -> np.ndarray:
    v = np.asarray(vocabulary, dtype=np.float32)
    if v.ndim != 2 or v.shape[1] != SIFT_DIM or len(v) == 0:
        raise ValueError(f"expected a vocabulary [words, {SIFT_DIM}], got {list(v.shape)}")
    if not (np.array_equal(v, np.rint(v)) and v.min() >= 0 and v.max() <= 255):
        raise ValueError("the vocabulary must hold integers in [0, 255] (exact distances need them)")
    return v


def nearest_words(descriptors: np.ndarray, vocabulary: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest word of each descriptor (int64 [n]; ties to the lower index) and the
    squared distance to it (int64 [n]).

    |x - c|^2 = |x|^2 - 2 x.c + |c|^2, and the search ranks -2 x.c + |c|^2 (|x|^2 is the same for
    every word). With x and c integers in [0, 255] over 128 dimensions, every partial sum of the
    product -2 x.c is an integer of magnitude at most 2 * 128 * 255^2 = 16,646,400 < 2^24, and
    float32 holds every integer up to 2^24 exactly: the BLAS product gives the same bits whatever
    its blocking, summation order or thread count. Adding |c|^2 <= 8,323,200 stays in that range."""
    x = _as_sift(descriptors)
    v = _check_vocabulary(vocabulary)
    neg2c = np.ascontiguousarray(-2.0 * v.T, dtype=np.float32)  # integers in [-510, 0]
    c2 = np.einsum("ij,ij->i", v, v).astype(np.float32)  # integers up to 128 * 255^2, exact
    labels = np.empty(len(x), np.int64)
    dist = np.empty(len(x), np.int64)
    rows = _chunk_rows(len(v))
    for start in range(0, len(x), rows):
        xf = x[start:start + rows].astype(np.float32)
        d = xf @ neg2c
        d += c2
        best = d.argmin(axis=1)  # first minimum: ties go to the lower index
        labels[start:start + rows] = best
        x2 = np.einsum("ij,ij->i", xf, xf)  # integers below 2^24: exact in any order
        dist[start:start + rows] = d[np.arange(len(xf)), best].astype(np.int64) + x2.astype(np.int64)
    return labels, dist


def _sample_rows(descriptors: list[np.ndarray], sample: int, rng: np.random.Generator) -> np.ndarray:
    """``sample`` descriptors drawn without replacement from all images (all of them if fewer),
    gathered image by image so that all descriptors are never copied into one array."""
    sizes = np.array([len(d) for d in descriptors], np.int64)
    total = int(sizes.sum())
    if total <= sample:
        return np.concatenate(descriptors) if descriptors else np.zeros((0, SIFT_DIM), np.uint8)
    picked = np.sort(rng.choice(total, sample, replace=False))
    starts = np.cumsum(sizes) - sizes
    image = np.searchsorted(starts, picked, side="right") - 1
    out = np.empty((sample, SIFT_DIM), np.uint8)
    for i in np.unique(image):
        rows = image == i
        out[rows] = descriptors[i][picked[rows] - starts[i]]
    return out


SEEDING_ROUNDS = 16
"""k-means++ picks its seeds in this many rounds (see :func:`_seed_centroids`)."""


def _seed_centroids(x: np.ndarray, words: int, rng: np.random.Generator) -> np.ndarray:
    """Up to ``words`` distinct rows of ``x`` as initial centroids, by k-means++ in batches.

    k-means++ (Arthur & Vassilvitskii 2007) draws each seed with probability D(x)^2 / sum D^2, D
    the distance to the nearest seed so far: seeds spread over the data, where uniform random
    seeds often put two in one cluster and one across two, which Lloyd's iterations never undo.
    One seed at a time costs ``words`` passes over the sample; here each of SEEDING_ROUNDS rounds
    draws a batch (without replacement) from the same D^2, which costs one Lloyd iteration in all
    and is plain k-means++ when ``words`` <= SEEDING_ROUNDS. A row equal to a seed has D = 0 and is
    never drawn, so the seeds are distinct and fewer than ``words`` only when ``x`` has fewer
    distinct rows."""
    seeds = [x[rng.integers(len(x))][None]]
    d2 = nearest_words(x, seeds[0].astype(np.float32))[1]
    count, batch = 1, -(-(words - 1) // SEEDING_ROUNDS)
    while count < words:
        candidates = int(np.count_nonzero(d2))
        if candidates == 0:
            break  # every row equals a seed: no more distinct words
        b = min(batch, words - count, candidates)
        picked = np.sort(rng.choice(len(x), b, replace=False, p=d2 / d2.sum()))
        new = x[picked]
        # two picks of one batch can be equal rows: keep the first of each value
        _, first = np.unique(new, axis=0, return_index=True)
        new = new[np.sort(first)]
        seeds.append(new)
        count += len(new)
        d2 = np.minimum(d2, nearest_words(x, new.astype(np.float32))[1])
    return np.concatenate(seeds).astype(np.float32)


def _update(x: np.ndarray, labels: np.ndarray, dist: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """New centroids: each the rounded mean of its points (integer sums, exact); an empty cluster
    takes the point farthest from its own centroid (ties to the lower index), the point the
    current words describe worst."""
    k = len(centroids)
    counts = np.bincount(labels, minlength=k)
    filled = counts > 0
    order = np.argsort(labels, kind="stable")
    starts = (np.cumsum(counts) - counts)[filled]
    sums = np.add.reduceat(x[order], starts, axis=0, dtype=np.int64)
    new = centroids.copy()
    new[filled] = np.rint(sums / counts[filled, None])  # mean in [0, 255]: stays integer and in range
    empty = np.flatnonzero(~filled)
    if len(empty):
        far = np.argsort(-dist, kind="stable")[:len(empty)]
        far = far[dist[far] > 0]  # a point on its centroid would copy that centroid
        new[empty[:len(far)]] = x[far]
    return new


def build_vocabulary(descriptors: list[np.ndarray], words: int, iterations: int = 8, sample: int = SAMPLE,
                     seed: int = 0) -> np.ndarray:
    """Visual words: k-means centroids (float32 [words, 128], integer-valued) of a seeded sample of
    at most ``sample`` descriptors; fewer words when the sample has fewer distinct descriptors.

    Lloyd's iterations from k-means++ seeds (:func:`_seed_centroids`), each centroid moved to
    the rounded mean of its points: rounding keeps the centroids integers, which makes every
    distance exact (:func:`nearest_words`), so the vocabulary is the same bits on any thread count.
    Stops early once no point changes word."""
    if words < 1:
        raise ValueError(f"a vocabulary needs at least one word, got {words}")
    rng = np.random.default_rng(seed)
    x = _sample_rows([_as_sift(d) for d in descriptors], sample, rng)
    if len(x) == 0:
        raise ValueError("no descriptors to build a vocabulary from")
    centroids = _seed_centroids(x, words, rng)
    labels = None
    for _ in range(iterations):
        new_labels, dist = nearest_words(x, centroids)
        if labels is not None and np.array_equal(labels, new_labels):
            break  # converged: the same assignment gives the same means
        labels = new_labels
        centroids = _update(x, labels, dist, centroids)
    return centroids


def assign_words(descriptors: list[np.ndarray], vocabulary: np.ndarray) -> list[np.ndarray]:
    """The word (int64 index into ``vocabulary``) of every descriptor of every image; exact, as
    :func:`nearest_words`."""
    return [nearest_words(d, vocabulary)[0] for d in descriptors]


def tfidf_vectors(words_per_image: list[np.ndarray], n_words: int) -> np.ndarray:
    """TF-IDF vectors (float64 [n_images, n_words]), each row of unit length or zero.

    tf(w, i) = count(w, i) / words in i; idf(w) = log(N / df(w)), df(w) the number of images
    containing w. A word in every image has idf 0: it tells no image from another. A word in no
    image gets idf 0 too (no division by zero), and an image with no words a zero row."""
    n = len(words_per_image)
    counts = np.zeros((n, n_words), np.float64)
    for i, w in enumerate(words_per_image):
        w = np.asarray(w, np.int64)
        if len(w) and (w.min() < 0 or w.max() >= n_words):
            raise ValueError(f"image {i} has word indices outside [0, {n_words})")
        counts[i] = np.bincount(w, minlength=n_words)
    totals = counts.sum(axis=1, keepdims=True)
    tf = counts / np.maximum(totals, 1.0)
    df = np.count_nonzero(counts, axis=0)
    idf = np.where(df > 0, np.log(n / np.maximum(df, 1)), 0.0)
    v = tf * idf
    norms = np.linalg.norm(v, axis=1, keepdims=True)
    return v / np.where(norms > 0, norms, 1.0)


def similarity(vectors: np.ndarray) -> np.ndarray:
    """Cosine similarity of the rows (float64 [n, n]), the diagonal -inf (an image is not its own
    match); a zero row is 0 to every other.

    Rows are normalised and rounded to integers q = rint(QUANTUM * u). Then |q|^2 <= (QUANTUM +
    sqrt(d) / 2)^2 < 2^53, so by Cauchy-Schwarz every partial sum of q_i . q_j is an integer below
    2^53, exact in float64 in any order: the ranking is the same bits on any thread count, where a
    float product's last bits can change with the BLAS blocking. Rounding moves a cosine by at most
    about sqrt(d) / QUANTUM (3e-5 for 1024 words)."""
    v = np.asarray(vectors, np.float64)
    norms = np.linalg.norm(v, axis=1, keepdims=True)
    q = np.rint(QUANTUM * (v / np.where(norms > 0, norms, 1.0)))
    sim = (q @ q.T) / float(QUANTUM) ** 2  # a power of two: exact
    np.fill_diagonal(sim, -np.inf)
    return sim


def ranked_neighbours(sim: np.ndarray, top_k: int) -> np.ndarray:
    """The ``top_k`` most similar other images of each image (int64 [n, min(top_k, n - 1)]), most
    similar first, equal similarities in index order (a stable sort)."""
    n = len(sim)
    k = max(0, min(top_k, n - 1))
    return np.argsort(-np.asarray(sim), axis=1, kind="stable")[:, :k]


def capture_is_ordered(sim: np.ndarray, top_k: int) -> bool:
    """Whether the name order is a capture order: image i + 1 is among the ``top_k`` most similar
    images of image i for at least half of the images (all but the last).

    A folder of photos sorted by name is usually the order they were taken (camera and phone file
    names count up, video frames are numbered), but not always: several cameras, renamed or merged
    folders. Retrieval tells: consecutive photos of a walk look alike, so most of them are each
    other's neighbours, while in a shuffled order image i + 1 is among i's top_k with probability
    top_k / (n - 1). Half, not all: a walk has turns, gaps and blurred frames. (A shuffled order can
    pass when top_k is about n / 2 or more; the sequential pairs are then mostly retrieved anyway.)"""
    n = len(sim)
    if n < 2:
        return False
    neighbours = ranked_neighbours(sim, top_k)
    hits = sum(int(i + 1 in neighbours[i]) for i in range(n - 1))
    return 2 * hits >= n - 1


def _named_pairs(names: list[str], pairs: set[tuple[int, int]]) -> list[tuple[str, str]]:
    """Index pairs (a < b) as name pairs, sorted by (a, b)."""
    return [(names[a], names[b]) for a, b in sorted(pairs)]


def retrieval_pairs(names: list[str], sim: np.ndarray, top_k: int = TOP_K,
                    sequential_overlap: int = 0) -> list[tuple[str, str]]:
    """Each image with its ``top_k`` most similar images and with the next ``sequential_overlap``
    images in name order; each unordered pair once, the earlier name (in ``names``) first, sorted
    by the two names' positions."""
    n = len(names)
    if np.shape(sim) != (n, n):
        raise ValueError(f"similarity is {list(np.shape(sim))} for {n} names")
    pairs = {(min(i, j), max(i, j)) for i, row in enumerate(ranked_neighbours(sim, top_k)) for j in row.tolist()}
    pairs |= {(i, j) for i in range(n) for j in range(i + 1, min(n, i + 1 + sequential_overlap))}
    return _named_pairs(names, pairs)


def more_pairs(names: list[str], sim: np.ndarray, images: list[str], top_k: int,
               done: set[frozenset]) -> list[tuple[str, str]]:
    """A second round for ``images`` (unregistered or weakly connected): each with its ``top_k``
    most similar images, except the unordered pairs in ``done`` (already matched). Pass a larger
    ``top_k`` than the first round's to reach images the first round did not try. Ordered as
    :func:`retrieval_pairs`."""
    index = {name: i for i, name in enumerate(names)}
    missing = [name for name in images if name not in index]
    if missing:
        raise KeyError(f"not among the names: {missing[:5]}")
    neighbours = ranked_neighbours(sim, top_k)
    pairs = set()
    for name in images:
        i = index[name]
        for j in neighbours[i].tolist():
            if frozenset((name, names[j])) not in done:
                pairs.add((min(i, j), max(i, j)))
    return _named_pairs(names, pairs)


def vocabulary_size(sample_size: int) -> int:
    """Words for a k-means sample of ``sample_size`` descriptors: DESCRIPTORS_PER_WORD each, at
    most MAX_WORDS, at least 1."""
    return int(min(MAX_WORDS, max(1, sample_size // DESCRIPTORS_PER_WORD)))


class RetrievalPlan(NamedTuple):
    pairs: list[tuple[str, str]]
    """Pairs to match, as :func:`retrieval_pairs` orders them."""
    sim: np.ndarray
    """Cosine similarity [n, n] of the TF-IDF vectors (diagonal -inf), for :func:`more_pairs`."""
    ordered: bool
    """Whether the name order was taken as a capture order (sequential pairs added)."""


def plan_pairs(database: Path, names: list[str], top_k: int = TOP_K, per_image: int = PER_IMAGE,
               words: int | None = None, sequential_overlap: int = SEQUENTIAL_OVERLAP, sample: int = SAMPLE,
               seed: int = 0) -> RetrievalPlan:
    """Retrieval pairs for the images ``names`` whose SIFT features are in ``database``: read
    descriptors, build the vocabulary (``words`` None: :func:`vocabulary_size` of the sample),
    TF-IDF vectors, similarity; sequential pairs only where :func:`capture_is_ordered`."""
    descriptors = read_descriptors(database, names, per_image, seed)
    if words is None:
        words = vocabulary_size(min(sample, sum(len(d) for d in descriptors)))
    vocabulary = build_vocabulary(descriptors, words, sample=sample, seed=seed)
    sim = similarity(tfidf_vectors(assign_words(descriptors, vocabulary), len(vocabulary)))
    ordered = capture_is_ordered(sim, top_k)
    pairs = retrieval_pairs(names, sim, top_k, sequential_overlap if ordered else 0)
    return RetrievalPlan(pairs, sim, ordered)
