"""Procedural textures: drawn per face from the seed, in metric units (TEXELS_PER_M).

A style per surface kind (wall, floor, ceiling, wood, paint, books, ...) sets the base
colour and how many shapes, text blobs, posters and specks a square metre carries, so
every face has corners for feature matching at any viewing distance.
"""

from __future__ import annotations

import math
import string

import cv2
import numpy as np

# Texture resolution (texels per metre): 5 mm texels stay about one pixel wide at 3 m.
TEXELS_PER_M = 200.0

_FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
          cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_PLAIN)
_CHARS = string.ascii_letters + string.digits + "#%&@?+"

# style: (base colour range low, high, shapes, text blobs, posters, specks; all per m^2)
_STYLES: dict[str, tuple[tuple[int, int, int], tuple[int, int, int], float, float, float, float]] = {
    "wall": ((150, 140, 120), (215, 210, 200), 28.0, 8.0, 0.45, 150.0),
    "floor": ((70, 60, 50), (150, 130, 110), 30.0, 3.0, 0.25, 150.0),
    "ceiling": ((170, 170, 165), (220, 220, 215), 20.0, 3.0, 0.3, 80.0),
    # Furniture is seen from a metre or less too: denser marks than on the walls, so a face
    # filling a quadrant of the image still holds its share of ORB's strongest corners.
    "wood": ((90, 60, 35), (170, 120, 80), 60.0, 10.0, 0.0, 600.0),
    "tabletop": ((90, 60, 35), (170, 120, 80), 60.0, 15.0, 0.0, 600.0),
    "paint": ((50, 50, 50), (200, 200, 200), 60.0, 10.0, 0.0, 600.0),
    "books": ((60, 45, 35), (120, 90, 70), 0.0, 0.0, 0.0, 0.0),
    "object": ((40, 40, 40), (220, 220, 220), 60.0, 20.0, 0.0, 150.0),
}


def _smooth_noise(rng: np.random.Generator, w: int, h: int, cell_px: float, sigma: float) -> np.ndarray:
    """Smooth random field (h, w, 3) float32 with features about ``cell_px`` texels wide:
    mostly brightness, a little colour (real surfaces are not rainbow-mottled)."""
    gw, gh = max(2, int(w / cell_px) + 2), max(2, int(h / cell_px) + 2)
    grid = (rng.normal(0.0, sigma, (gh, gw, 1)) + rng.normal(0.0, sigma / 4, (gh, gw, 3)))
    return cv2.resize(grid.astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)


def _random_colour(rng: np.random.Generator, avoid: np.ndarray) -> tuple[int, int, int]:
    """A colour clearly different in brightness from ``avoid`` so FAST sees its edges."""
    for _ in range(8):
        c = rng.integers(0, 256, 3)
        if abs(float(c.mean()) - float(avoid.mean())) > 45:
            break
    return int(c[0]), int(c[1]), int(c[2])


def _random_text(rng: np.random.Generator) -> str:
    return "".join(rng.choice(list(_CHARS), int(rng.integers(3, 11))))


def _draw_text(rng: np.random.Generator, img: np.ndarray, x: int, y: int, height_px: float,
               colour: tuple[int, int, int]) -> None:
    font = _FONTS[int(rng.integers(len(_FONTS)))]
    scale = max(0.3, height_px / 22.0)
    thickness = max(1, int(round(scale * 1.8)))
    cv2.putText(img, _random_text(rng), (x, y), font, scale, colour, thickness, cv2.LINE_AA)


def _draw_shape(rng: np.random.Generator, img: np.ndarray, base: np.ndarray,
                size_m: tuple[float, float]) -> None:
    """One random rectangle, circle, ellipse, line, polygon or cluster of dots."""
    h, w = img.shape[:2]
    s = float(np.exp(rng.uniform(np.log(size_m[0]), np.log(size_m[1])))) * TEXELS_PER_M
    x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
    colour = _random_colour(rng, base)
    kind = int(rng.integers(7))
    filled = -1 if rng.random() < 0.6 else max(1, int(s / 12))
    if kind == 0:
        a = s * rng.uniform(0.3, 1.0)
        cv2.rectangle(img, (int(x - s / 2), int(y - a / 2)), (int(x + s / 2), int(y + a / 2)),
                      colour, filled, cv2.LINE_AA)
    elif kind == 1:
        cv2.circle(img, (x, y), max(2, int(s / 2)), colour, filled, cv2.LINE_AA)
    elif kind == 2:
        axes = (max(2, int(s / 2)), max(2, int(s / 2 * rng.uniform(0.3, 0.9))))
        cv2.ellipse(img, (x, y), axes, float(rng.uniform(0, 180)), 0, 360, colour, filled, cv2.LINE_AA)
    elif kind == 3:
        angle = rng.uniform(0, np.pi)
        dx, dy = s * np.cos(angle), s * np.sin(angle)
        cv2.line(img, (int(x - dx), int(y - dy)), (int(x + dx), int(y + dy)), colour,
                 max(2, int(s / 10)), cv2.LINE_AA)
    elif kind == 4:
        n = int(rng.integers(3, 6))
        pts = np.array([x, y]) + rng.uniform(-s / 2, s / 2, (n, 2))
        cv2.fillPoly(img, [pts.astype(np.int32)], colour, cv2.LINE_AA)
    elif kind == 5:
        for _ in range(int(rng.integers(3, 8))):
            px, py = x + rng.normal(0, s / 2), y + rng.normal(0, s / 2)
            cv2.circle(img, (int(px), int(py)), max(2, int(s / 8)), colour, -1, cv2.LINE_AA)
    else:
        _draw_text(rng, img, x, y, max(8.0, s / 3), colour)


def _draw_specks(rng: np.random.Generator, img: np.ndarray, base: np.ndarray, per_m2: float) -> None:
    """Many small dots and dashes (0.6-2 cm): corners for close views, where the larger
    shapes are too sparse. Parameters are drawn at once; only the drawing loops."""
    h, w = img.shape[:2]
    n = int(rng.poisson(per_m2 * w * h / TEXELS_PER_M**2))
    xy = np.stack([rng.integers(0, w, n), rng.integers(0, h, n)], axis=1)
    size = rng.uniform(0.006, 0.02, n) * TEXELS_PER_M
    step = (size[:, None] * rng.uniform(-1.0, 1.0, (n, 2))).astype(np.int32)
    dark = rng.random(n) < (0.75 if base.mean() > 110 else 0.25)
    shade = np.where(dark[:, None], rng.integers(0, 90, (n, 3)), rng.integers(170, 256, (n, 3)))
    square = rng.random(n) < 0.5
    for (x, y), s, (dx, dy), c, sq in zip(xy.tolist(), size.tolist(), step.tolist(),
                                          shade.tolist(), square.tolist()):
        if sq:
            cv2.rectangle(img, (x, y), (x + dx, y + dy), c, -1)
        else:
            cv2.circle(img, (x, y), max(1, int(s / 2)), c, -1, cv2.LINE_AA)


def _draw_poster(rng: np.random.Generator, img: np.ndarray) -> None:
    """A framed light rectangle with a title, shapes and rows of small text."""
    h, w = img.shape[:2]
    pw = int(rng.uniform(0.3, 0.9) * TEXELS_PER_M)
    ph = int(pw * rng.uniform(0.6, 1.5))
    if pw >= w - 4 or ph >= h - 4:
        return
    x0, y0 = int(rng.integers(0, w - pw)), int(rng.integers(0, h - ph))
    paper = rng.integers(200, 250, 3)
    sub = img[y0:y0 + ph, x0:x0 + pw]
    sub[:] = paper.astype(np.uint8)
    cv2.rectangle(sub, (0, 0), (pw - 1, ph - 1), _random_colour(rng, paper), max(2, pw // 60))
    for _ in range(int(rng.integers(3, 9))):
        _draw_shape(rng, sub, paper, (0.03, 0.2))
    ink = (int(rng.integers(0, 80)), int(rng.integers(0, 80)), int(rng.integers(0, 80)))
    line_h = int(rng.uniform(0.015, 0.03) * TEXELS_PER_M)
    for row in range(int(rng.integers(2, 6))):
        y = int(ph * 0.6) + row * int(line_h * 1.6)
        if y < ph - 4:
            _draw_text(rng, sub, int(pw * 0.08), y, line_h, ink)


def _draw_books(rng: np.random.Generator, img: np.ndarray) -> None:
    """The spines of a row of books filling the face: random width, colour and height (the
    shelf boards are geometry), labels, and the odd gap."""
    h, w = img.shape[:2]
    x = 0
    while x < w:
        bw = int(rng.uniform(0.015, 0.07) * TEXELS_PER_M)
        if rng.random() < 0.08:  # gaps and leaning books break any rhythm
            x += bw
            continue
        top = int(h * rng.uniform(0.0, 0.25))
        colour = tuple(int(c) for c in rng.integers(20, 240, 3))
        cv2.rectangle(img, (x, top), (x + bw - 1, h - 1), colour, -1)
        if bw > 6 and rng.random() < 0.7:
            label = tuple(int(255 - c) for c in colour)
            ly = int(top + (h - top) * rng.uniform(0.15, 0.6))
            cv2.rectangle(img, (x + 1, ly), (x + bw - 2, ly + max(2, bw // 2)), label, -1)
        x += bw + int(rng.integers(0, 3))


def paint_texture(rng: np.random.Generator, width_m: float, height_m: float, style: str) -> np.ndarray:
    """Texture image (H, W, 3) uint8 RGB of a ``width_m`` x ``height_m`` face."""
    w = max(2, int(math.ceil(width_m * TEXELS_PER_M)))
    h = max(2, int(math.ceil(height_m * TEXELS_PER_M)))
    lo, hi, shapes, texts, posters, specks = _STYLES[style]
    base = rng.uniform(np.asarray(lo, float), np.asarray(hi, float))
    # Blotches (~40 cm) and mottling (~4 cm): bare areas still carry some structure.
    field = (base.astype(np.float32) + _smooth_noise(rng, w, h, 0.4 * TEXELS_PER_M, 14.0)
             + _smooth_noise(rng, w, h, 0.04 * TEXELS_PER_M, 7.0))
    img = np.clip(field, 0, 255).astype(np.uint8)
    area = width_m * height_m
    if style == "books":
        _draw_books(rng, img)
    else:
        _draw_specks(rng, img, base, specks)
    for _ in range(int(rng.poisson(shapes * area))):
        _draw_shape(rng, img, base, (0.02, 0.3))
    for _ in range(int(rng.poisson(texts * area))):
        colour = _random_colour(rng, base)
        _draw_text(rng, img, int(rng.integers(0, w)), int(rng.integers(0, h)),
                   rng.uniform(0.02, 0.07) * TEXELS_PER_M, colour)
    for _ in range(int(rng.poisson(posters * area))):
        _draw_poster(rng, img)
    # Soften drawn edges to about one texel so distant views do not shimmer.
    return cv2.GaussianBlur(img, (3, 3), 0.7)
