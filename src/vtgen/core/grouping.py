"""Split groups: images joined by union-find, and the exact and near-duplicates that join them.

Near-duplicates are found on 16 x 16 greyscale thumbnails (:func:`grey_thumbnail`,
:func:`near_duplicate_blocks`). Everything here works on arrays of codes and thumbnails; the ingest
stage (:func:`vtgen.stages.ingest.assign_groups`) builds them from the manifest and words the warnings.
"""

from __future__ import annotations

import cv2
import numpy as np

THUMB = 16  # side of the greyscale thumbnail compared for near-duplicates


def grey_thumbnail(array: np.ndarray) -> np.ndarray:
    """The THUMB x THUMB greyscale (area-averaged) thumbnail, uint8, of an (H, W) or (H, W, 3) image."""
    grey = array if array.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(array), cv2.COLOR_RGB2GRAY)
    height, width = grey.shape
    fy, fx = height // THUMB, width // THUMB
    if fx >= 3 and fy >= 3 and fx * THUMB == width and fy * THUMB == height and fx * fy <= 65536:
        # an integer shrink (640x480: 40 x 30 pixels per cell): OpenCV's INTER_AREA rounds each cell's
        # exact sum times float32(1 / cell area), half to even; the sums by cv2.reduce, 2-3x faster
        rows = cv2.reduce(np.ascontiguousarray(grey).reshape(height * THUMB, fx), 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S)
        sums = rows.reshape(THUMB, fy, THUMB).sum(axis=1)
        return np.rint(sums.astype(np.float32) * np.float32(1.0 / (fx * fy))).astype(np.uint8)
    return cv2.resize(grey, (THUMB, THUMB), interpolation=cv2.INTER_AREA)


class UnionFind:
    """Disjoint sets over ``0..n-1``; a set's root is its smallest member joined so far."""

    def __init__(self, n: int):
        self.parent = np.arange(n)

    def find(self, i: int) -> int:
        parent = self.parent
        root = i
        while parent[root] != root:
            root = parent[root]
        while parent[i] != root:
            parent[i], i = root, parent[i]
        return root

    def union(self, i: int, j: int) -> bool:
        a, b = self.find(i), self.find(j)
        if a == b:
            return False
        self.parent[max(a, b)] = min(a, b)
        return True

    def roots(self) -> np.ndarray:
        """The root of every member, int64."""
        n = len(self.parent)
        return np.fromiter((self.find(i) for i in range(n)), dtype=np.int64, count=n)


def union_equal(uf: UnionFind, codes: np.ndarray) -> None:
    """Join every index to the first index holding the same code (codes < 0 join nothing)."""
    codes = np.asarray(codes)
    _, first, inverse = np.unique(codes, return_index=True, return_inverse=True)
    for i, head in enumerate(first[inverse].tolist()):
        if codes[i] >= 0 and head != i:
            uf.union(head, i)


def near_duplicate_blocks(thumbs: np.ndarray, rms: float, relative: float, index=None, block: int = 32):
    """Yield ``(rows, cols, hits)``: index arrays into ``thumbs`` (restricted to ``index`` when given)
    and a boolean matrix marking the
    near-duplicate pairs among them (each unordered pair appears once, never an image with itself).

    Two images are near-duplicates when the RMS difference of their greyscale thumbnails is at most
    ``rms`` grey levels and at most ``relative`` times their contrast (the standard deviation of the
    thumbnails about their means, pooled). The second condition keeps apart the thumbnails of fine
    textures, which look flat at 16 px. Thumbnails are sorted by mean brightness and only blocks
    whose means lie within ``rms`` are compared (the RMS difference is at least the difference of
    the means); ``block`` x ``block`` pairs are compared at a time, so memory does not grow with
    the number of images.
    """
    index = np.arange(len(thumbs)) if index is None else np.asarray(index)
    n = len(index)
    if n < 2 or rms <= 0:
        return
    flat = thumbs.reshape(len(thumbs), -1)
    d = flat.shape[1]
    means, variances = np.empty(n, np.float32), np.empty(n, np.float32)
    for start in range(0, n, block):  # in blocks: a float copy of every thumbnail would be 1 KiB per image
        chunk = flat[index[start:start + block]].astype(np.float32)
        means[start:start + block], variances[start:start + block] = chunk.mean(axis=1), chunk.var(axis=1)
    del chunk
    order = np.argsort(means, kind="stable")
    index, means, variances = index[order], means[order], variances[order]
    norms = variances * d + means * means * d  # sum of squares of each thumbnail
    for start in range(0, n, block):
        stop = min(n, start + block)
        rows = flat[index[start:stop]].astype(np.float32)
        reach = int(np.searchsorted(means, means[stop - 1] + rms, side="right"))
        for col in range(start, reach, block):
            end = min(reach, col + block)
            cols = rows if col == start else flat[index[col:end]].astype(np.float32)
            dist2 = (norms[start:stop, None] + norms[None, col:end] - 2 * (rows @ cols.T)) / d
            pooled = (variances[start:stop, None] + variances[None, col:end]) / 2
            hits = (dist2 <= rms * rms + 1e-3) & (dist2 <= relative * relative * pooled + 1e-3)
            if col == start:
                hits = np.triu(hits, k=1)  # each pair once, no image with itself
            if hits.any():
                yield index[start:stop], index[col:end], hits


def near_duplicate_pairs(thumbs: np.ndarray, rms: float, relative: float) -> list[tuple[int, int]]:
    """All near-duplicate index pairs ``(i, j)``, ``i < j`` (:func:`near_duplicate_blocks`); for small sets."""
    pairs = []
    for rows, cols, hits in near_duplicate_blocks(thumbs, rms, relative):
        for a, b in zip(*np.nonzero(hits)):
            pairs.append(tuple(sorted((int(rows[a]), int(cols[b])))))
    return sorted(pairs)


def merge_exact_duplicates(uf: UnionFind, md5_codes: np.ndarray, cls_codes: np.ndarray, examples: int
                           ) -> tuple[np.ndarray, int, list[tuple[int, int]]]:
    """Join the images of one class with the same content code (MD5); count the images whose bytes
    were already seen in another class.

    Returns (mask of the images with an exact duplicate in their class, that count, the first
    ``examples`` such ``(earlier image, image)`` index pairs)."""
    exact = np.zeros(len(md5_codes), dtype=bool)
    cross, found = 0, []
    first_in_class: dict[tuple[int, int], int] = {}
    first_any: dict[int, int] = {}
    for i in range(len(md5_codes)):
        key = (md5_codes[i], cls_codes[i])
        if key in first_in_class:
            exact[i] = exact[first_in_class[key]] = True
            uf.union(first_in_class[key], i)
        else:
            first_in_class[key] = i
            j = first_any.setdefault(md5_codes[i], i)
            if j != i:  # the same bytes already seen in another class
                cross += 1
                if cross <= examples:
                    found.append((j, i))
    return exact, cross, found


def merge_near_duplicates(uf: UnionFind, thumbs: np.ndarray, rows_of: dict, cls_codes: np.ndarray,
                          md5_codes: np.ndarray, rms: float, relative: float, examples: int
                          ) -> tuple[np.ndarray, int, list[tuple[str, int, int]]]:
    """Join the near-duplicates (:func:`near_duplicate_blocks`) of one class within each group of
    rows (``rows_of``: modality -> row indices); count the near-duplicate pairs across classes.

    Returns (mask of the images with a near-duplicate of other content in their class, that count,
    the first ``examples`` such ``(modality, i, j)`` pairs)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    near = np.zeros(len(cls_codes), dtype=bool)
    cross, found = 0, []
    for modality, rows in rows_of.items():
        for r, c, hits in near_duplicate_blocks(thumbs, rms, relative, index=rows):
            same = cls_codes[r][:, None] == cls_codes[c][None, :]
            merge = hits & same
            new = merge & (md5_codes[r][:, None] != md5_codes[c][None, :])
            near[r[new.any(axis=1)]] = True
            near[c[new.any(axis=0)]] = True
            if merge.any():
                a, b = np.nonzero(merge)
                nodes = np.concatenate([r, c])
                graph = coo_matrix((np.ones(len(a)), (a, len(r) + b)), shape=(len(nodes), len(nodes)))
                _, labels = connected_components(graph, directed=False)
                firsts: dict[int, int] = {}
                for node, label in zip(nodes, labels):
                    uf.union(firsts.setdefault(int(label), int(node)), int(node))
            across = hits & ~same
            if across.any():
                for a, b in zip(*np.nonzero(across)):
                    cross += 1
                    if cross <= examples:
                        found.append((modality, int(r[a]), int(c[b])))
    return near, cross, found


def group_names(uf: UnionFind, keys: list[str]) -> tuple[list[str], int]:
    """(each member's group name, the number of groups): a group is named after its smallest key."""
    roots = uf.roots().tolist()
    name_of: dict[int, str] = {}
    for i, root in enumerate(roots):
        if root not in name_of or keys[i] < name_of[root]:
            name_of[root] = keys[i]
    return [name_of[root] for root in roots], len(name_of)
