"""Labels of a movie frame, laid out so that they never overlap, drawn over the 3D
picture with Pillow (exact text extents from the font; DejaVu Sans, shipped with
matplotlib).

Layout of a W x H frame (margin m = 2% of H, at least 6 px):

    top band      title (left, wrapped to at most two lines, shortened with "..."
                  beyond)            |  time label (right, the width of the widest one)
    window        the vesicles (the camera keeps every drawn point inside it)
    bottom band   axes triad (left)  |  colour bar title, bar, three value labels (right)

Boxes are pixel rectangles (left, top, right, bottom) of the image (origin at the
top-left corner, right and bottom exclusive).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

_AXIS_COLORS = ((200, 40, 40), (30, 150, 30), (40, 70, 210))


@lru_cache(maxsize=None)
def _font(px):
    from matplotlib import font_manager
    from PIL import ImageFont
    path = font_manager.findfont(font_manager.FontProperties(family="DejaVu Sans"), fallback_to_default=False)
    return ImageFont.truetype(path, int(px))


def text_extent(text, px):
    """(left, top, right, bottom) of text drawn at (0, 0) with anchor "la", font size px."""
    return _font(px).getbbox(text, anchor="la")


def _width(text, px):
    b = text_extent(text, px)
    return b[2] - min(b[0], 0)


def wrap_title(title, max_width, px, max_lines=2):
    """Lines of `title` (words kept whole where possible) that each fit in max_width
    pixels; more than max_lines lines are cut, the last one ending with "..."."""
    words = title.split()
    lines, cur = [], ""
    for w in words:
        trial = f"{cur} {w}" if cur else w
        if _width(trial, px) <= max_width:
            cur = trial
            continue
        if cur:
            lines.append(cur)
        cur = w
        while _width(cur, px) > max_width and len(cur) > 1:       # one word wider than the line
            k = len(cur)
            while k > 1 and _width(cur[:k], px) > max_width:
                k -= 1
            lines.append(cur[:k])
            cur = cur[k:]
    if cur:
        lines.append(cur)
    if len(lines) > max_lines:
        last = lines[max_lines - 1]
        while last and _width(last + "...", px) > max_width:
            last = last[:-1].rstrip()
        lines = lines[:max_lines - 1] + [last + "..."]
    return lines


def time_formatter(times):
    """Format "t = ..." with the fewest decimals (at most 6) that keep every frame time
    within 5% of the frame spacing."""
    t = np.asarray(times, dtype=float)
    steps = np.diff(np.unique(t))
    dec = 0
    if steps.size:
        tol = 0.05 * steps.min()
        while dec < 6 and np.max(np.abs(np.round(t, dec) - t)) > tol:
            dec += 1
    return lambda x: f"t = {x:.{dec}f}"


def _fmt_value(v):
    return f"{v:.3g}"


def _intersects(a, b):
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


@dataclass
class Layout:
    size: tuple
    margin: int
    title_lines: list
    boxes: dict = field(default_factory=dict)     # name -> (left, top, right, bottom)
    window: tuple = (-1.0, 1.0, -1.0, 1.0)        # vesicles: x0, x1, y0, y1 in NDC
    title_px: int = 0
    small_px: int = 0
    time_width: int = 0

    def window_pixels(self):
        W, H = self.size
        x0, x1, y0, y1 = self.window
        return (round((x0 + 1) / 2 * W), round((1 - y1) / 2 * H), round((x1 + 1) / 2 * W), round((1 - y0) / 2 * H))

    def overlapping(self):
        """Pairs of label boxes that intersect (empty for a valid layout)."""
        names = sorted(self.boxes)
        return [(a, b) for i, a in enumerate(names) for b in names[i + 1:]
                if _intersects(self.boxes[a], self.boxes[b])]


def make_layout(size, title, time_labels, bar=None, triad=True):
    """Layout of a frame of `size` (W, H).  title: str or None; time_labels: every time
    string of the movie (the widest sets the reserved width); bar: (title, lo, hi) of
    the colour bar or None."""
    W, H = size
    m = max(6, round(0.02 * H))
    big, small = int(np.clip(round(0.033 * H), 10, 40)), int(np.clip(round(0.026 * H), 8, 32))
    lay = Layout(size=(W, H), margin=m, title_lines=[], title_px=big, small_px=small)
    # top band: time label at the right, the title in the rest
    tw = max(_width(s, big) for s in time_labels)
    th = max(text_extent(s, big)[3] for s in time_labels)
    lay.time_width = tw
    lay.boxes["time"] = (W - m - tw, m, W - m, m + th)
    top = m + th
    if title:
        lay.title_lines = wrap_title(title, W - 3 * m - tw, big)
        lh = round(1.25 * big)
        tb = [text_extent(s, big) for s in lay.title_lines]
        right = m + max(b[2] for b in tb)
        bottom = m + lh * (len(tb) - 1) + tb[-1][3]
        lay.boxes["title"] = (m, m, right, bottom)
        top = max(top, bottom)
    # bottom band: triad at the left, colour bar at the right
    bar_h = max(8, round(0.025 * H))
    lab_h = text_extent("0123456789.-e", small)[3]
    band = max(bar_h + m // 2 + lab_h, round(0.14 * H) if triad else 0)
    y1 = H - m
    y0 = y1 - band
    if triad:
        lay.boxes["triad"] = (m, y0, m + band, y1)
    if bar is not None:
        name, lo, hi = bar
        bar_w = round(0.28 * W)
        bx1 = W - m - _width(_fmt_value(hi), small) // 2
        bx0 = bx1 - bar_w
        by0 = y0 + (band - bar_h - m // 2 - lab_h) // 2
        lay.boxes["colorbar"] = (bx0, by0, bx1, by0 + bar_h)
        lw = [_width(_fmt_value(v), small) for v in (lo, 0.5 * (lo + hi), hi)]
        lay.boxes["colorbar_labels"] = (bx0 - lw[0] // 2, by0 + bar_h + m // 2, bx1 + lw[2] - lw[2] // 2,
                                        by0 + bar_h + m // 2 + lab_h)
        nw = _width(name, small)
        nb = text_extent(name, small)
        ny = by0 + bar_h // 2 - (nb[3] + nb[1]) // 2
        lay.boxes["colorbar_title"] = (bx0 - m - nw, ny + nb[1], bx0 - m, ny + nb[3])
    bottom_free = y0
    # the window of the vesicles: between the bands, a margin from every label
    gap = m
    px0, py0, px1, py1 = m, top + gap, W - m, bottom_free - gap
    if py1 - py0 < 0.3 * H:
        raise ValueError(f"render: size {W}x{H} leaves too little room for the vesicles under the labels; "
                         f"use a larger --size")
    lay.window = (2 * px0 / W - 1, 2 * px1 / W - 1, 1 - 2 * py1 / H, 1 - 2 * py0 / H)
    outside = [n for n, b in lay.boxes.items() if b[0] < 0 or b[1] < 0 or b[2] > W or b[3] > H]
    if lay.overlapping() or outside:
        raise ValueError(f"render: size {W}x{H} is too small for the labels "
                         f"({', '.join(outside) or ' and '.join(lay.overlapping()[0])}); use a larger --size")
    return lay


class Overlay:
    """Draws the labels of a layout over frames (RGB uint8 arrays of the layout's size)."""

    def __init__(self, layout, *, title=True, bar=None, cmap=None, text_color=(0, 0, 0)):
        from PIL import Image, ImageDraw
        self.lay = layout
        self.color = tuple(text_color)
        W, H = layout.size
        self._static = Image.new("RGBA", (W, H), (0, 0, 0, 0))
        d = ImageDraw.Draw(self._static)
        if title and layout.title_lines:
            l, t = layout.boxes["title"][:2]
            for k, line in enumerate(layout.title_lines):
                d.text((l, t + k * round(1.25 * layout.title_px)), line, font=_font(layout.title_px),
                       fill=self.color, anchor="la")
        if bar is not None:
            name, lo, hi = bar
            from matplotlib import colormaps
            x0, y0, x1, y1 = layout.boxes["colorbar"]
            rgba = (colormaps[cmap](np.linspace(0, 1, x1 - x0)) * 255).astype(np.uint8)
            strip = np.repeat(rgba[None], y1 - y0, axis=0)
            self._static.paste(Image.fromarray(strip, "RGBA"), (x0, y0))
            d.rectangle((x0 - 1, y0 - 1, x1, y1), outline=self.color)
            ly = layout.boxes["colorbar_labels"][1]
            f = _font(layout.small_px)
            for v, x, anchor in ((lo, x0, "ma"), (0.5 * (lo + hi), (x0 + x1) // 2, "ma"), (hi, x1, "ma")):
                d.text((x, ly), _fmt_value(v), font=f, fill=self.color, anchor=anchor)
            nx, ny = layout.boxes["colorbar_title"][2], layout.boxes["colorbar"][1]
            d.text((nx, (y0 + y1) // 2), name, font=f, fill=self.color, anchor="rm")

    def _triad(self, draw, camera):
        """Axes x, y, z seen from the camera (orthographic directions), in the triad box."""
        pos, foc, up = (np.asarray(v, dtype=float) for v in camera)
        back = (pos - foc) / np.linalg.norm(pos - foc)
        right = np.cross(-back, up)
        right /= np.linalg.norm(right)
        upv = np.cross(right, -back)
        l, t, r, b = self.lay.boxes["triad"]
        s = r - l
        cx, cy = l + s / 2, t + s / 2
        L = 0.32 * s
        f = _font(self.lay.small_px)
        order = np.argsort([e @ back for e in np.eye(3)])       # farthest first
        for k in order:
            e = np.eye(3)[k]
            dx, dy = e @ right, -(e @ upv)
            end = (cx + L * dx, cy + L * dy)
            draw.line((cx, cy) + end, fill=_AXIS_COLORS[k], width=max(2, s // 30))
            lab = (cx + (L + 0.5 * self.lay.small_px) * dx, cy + (L + 0.5 * self.lay.small_px) * dy)
            draw.text(lab, "xyz"[k], font=f, fill=_AXIS_COLORS[k], anchor="mm")

    def draw(self, img, time_text, camera=None):
        """img (H, W, 3) uint8 -> the same picture with the labels."""
        from PIL import Image, ImageDraw
        base = Image.fromarray(np.ascontiguousarray(img[:, :, :3])).convert("RGBA")
        base.alpha_composite(self._static)
        d = ImageDraw.Draw(base)
        r, t = self.lay.boxes["time"][2], self.lay.boxes["time"][1]
        d.text((r, t), time_text, font=_font(self.lay.title_px), fill=self.color, anchor="ra")
        if camera is not None and "triad" in self.lay.boxes:
            self._triad(d, camera)
        return np.asarray(base.convert("RGB"))
