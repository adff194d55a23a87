"""Checks that a drawn figure can be read: tick labels apart, legends legible and off the data.

Each function draws the figure (with Agg if it has no canvas yet) and answers with what is
wrong, an empty list when nothing is; the tests of the figures assert on these answers.
"""

from __future__ import annotations

import itertools

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import Collection, PathCollection
from matplotlib.figure import Figure
from matplotlib.legend import Legend
from matplotlib.patches import Rectangle
from matplotlib.transforms import Bbox

__all__ = ["draw", "line_points_px", "marker_points_px", "overlapping_tick_labels", "legend_font_too_small",
           "box_covers_data", "legend_covers_data"]


def draw(fig):
    """Draw ``fig`` and return its renderer.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        A figure without a canvas that can render gets an Agg canvas first.

    Returns
    -------
    matplotlib.backend_bases.RendererBase
        The renderer the figure was drawn with.
    """
    if not isinstance(fig.canvas, FigureCanvasAgg):
        FigureCanvasAgg(fig)
    fig.canvas.draw()
    return fig.canvas.get_renderer()


def _inside(xy: np.ndarray, box) -> np.ndarray:
    return (xy[:, 0] >= box.x0) & (xy[:, 0] <= box.x1) & (xy[:, 1] >= box.y0) & (xy[:, 1] <= box.y1)


def _densify(xy: np.ndarray, step_px: float, max_per_segment: int = 4000) -> np.ndarray:
    """Points at most ``step_px`` apart along the segments between consecutive finite points."""
    finite = np.all(np.isfinite(xy), axis=1)
    if len(xy) < 2:
        return xy[finite]
    seg = finite[:-1] & finite[1:]  # a NaN breaks the drawn path
    a, d = xy[:-1][seg], np.diff(xy, axis=0)[seg]
    n = np.clip(np.ceil(np.hypot(d[:, 0], d[:, 1]) / step_px), 1, max_per_segment).astype(int)
    i = np.repeat(np.arange(len(a)), n)
    t = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / n[i]
    return np.vstack([a[i] + d[i] * t[:, None], xy[finite]])


def line_points_px(line, step_px: float = 1.0) -> np.ndarray:
    """Display points along the drawn path of a line, inside its axes.

    Parameters
    ----------
    line : matplotlib.lines.Line2D
        A line of an axes; its drawstyle (steps) is followed and a NaN breaks it.
    step_px : float
        Largest distance between consecutive points, in pixels.

    Returns
    -------
    numpy.ndarray
        ``(n, 2)`` display coordinates; empty when the line has no line style.
    """
    if line.get_linestyle() in ("None", "none", " ", "") or not len(line.get_xdata()):
        return np.empty((0, 2))
    xy = line.get_transform().transform(np.asarray(line.get_path().vertices, float))
    xy = _densify(xy, step_px)
    return xy[_inside(xy, line.axes.get_window_extent())]


def marker_points_px(line) -> np.ndarray:
    """Display centres of a line's markers inside its axes, as ``(n, 2)`` (empty without markers).

    Parameters
    ----------
    line : matplotlib.lines.Line2D
        A line of an axes.

    Returns
    -------
    numpy.ndarray
        ``(n, 2)`` display coordinates of the finite data points.
    """
    if line.get_marker() in ("None", "none", " ", "", None) or not len(line.get_xdata()):
        return np.empty((0, 2))
    xy = line.get_transform().transform(np.asarray(line.get_xydata(), float))
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    return xy[_inside(xy, line.axes.get_window_extent())]


def overlapping_tick_labels(ax) -> list[tuple[str, str]]:
    """Pairs of tick labels whose drawn boxes overlap.

    Parameters
    ----------
    ax : matplotlib.axes.Axes or matplotlib.figure.Figure
        An axes, or a figure whose every axes is checked.

    Returns
    -------
    list of tuple of str
        The texts of each overlapping pair, per axis, major and minor labels together
        (visible, non-empty labels inside the figure).
    """
    fig = ax if isinstance(ax, Figure) else ax.figure
    axes = fig.axes if isinstance(ax, Figure) else [ax]
    r = draw(fig)
    bad = []
    for a in axes:
        for axis in (a.xaxis, a.yaxis):  # a log axis labels its minor ticks
            labs = [t for t in axis.get_ticklabels(which="both")
                    if t.get_visible() and t.get_text() and t.get_window_extent(r).overlaps(fig.bbox)]
            boxes = [t.get_window_extent(r) for t in labs]
            bad += [(labs[i].get_text(), labs[j].get_text())
                    for i, j in itertools.combinations(range(len(labs)), 2) if boxes[i].overlaps(boxes[j])]
    return bad


def _legend_of(ax_or_legend) -> Legend:
    leg = ax_or_legend if isinstance(ax_or_legend, Legend) else ax_or_legend.get_legend()
    if leg is None:
        raise ValueError("the axes have no legend")
    return leg


def legend_font_too_small(ax_or_legend, min_pt: float = 7) -> list[str]:
    """Legend texts smaller than ``min_pt`` points.

    Parameters
    ----------
    ax_or_legend : matplotlib.axes.Axes or matplotlib.legend.Legend
        A legend, or axes that have one (``ValueError`` if they have none).
    min_pt : float
        Smallest legible size, in points.

    Returns
    -------
    list of str
        The texts below the size, each as ``"text (size pt)"``.
    """
    return [f"{t.get_text()} ({t.get_fontsize():g} pt)" for t in _legend_of(ax_or_legend).get_texts()
            if t.get_fontsize() < min_pt]


def box_covers_data(ax, box, *, margin_px: float = 0.0, lines: bool = True, patches: bool = True,
                    collections: bool = True) -> list:
    """The data of ``ax`` that a box (a legend, a text) lies over.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        Axes already drawn (see `draw`).
    box : matplotlib.transforms.Bbox
        Display coordinates.
    margin_px : float
        The box is shrunk by this many pixels on each side (anti-aliased edges touch).
    lines : bool
        Check visible lines: points along their drawn path (1 px apart) and their markers
        (a marker counts when its glyph reaches into the box).
    patches : bool
        Check visible rectangles (bars, cells) of non-zero size, within the axes.
    collections : bool
        Check visible collections: scatter markers (reaching into the box), and polygons (bands,
        regions) whose outline passes under the box or whose filled area lies under it.

    Returns
    -------
    list
        The covered artists, each once, in the order of ``ax.get_children()``.
    """
    inner = box.padded(-margin_px)
    frame = ax.get_window_extent()
    hits = []
    for art in ax.get_children():
        if not art.get_visible():
            continue
        if lines and art in ax.lines:
            if _inside(line_points_px(art), inner).any():
                hits.append(art)
                continue
            m = marker_points_px(art)
            if len(m):
                r = art.get_markersize() * ax.figure.dpi / 72 / 2  # marker radius, px
                if _inside(m, inner.padded(r)).any():
                    hits.append(art)
        elif patches and isinstance(art, Rectangle) and art in ax.patches:
            ext = art.get_window_extent()
            shown = Bbox.intersection(ext, frame)
            if ext.width > 0 and ext.height > 0 and shown is not None and shown.overlaps(inner):
                hits.append(art)
        elif collections and isinstance(art, Collection) and art in ax.collections:
            if _collection_hit(art, inner, frame):
                hits.append(art)
    return hits


def _collection_hit(coll, inner, frame) -> bool:
    if isinstance(coll, PathCollection):  # scatter: a marker at each offset
        xy = coll.get_offset_transform().transform(np.asarray(coll.get_offsets(), float))
        xy = xy[np.all(np.isfinite(xy), axis=1)]
        sizes = coll.get_sizes()
        r = np.sqrt(np.max(sizes)) / 2 * coll.figure.dpi / 72 if len(sizes) else 0.0  # marker radius, px
        return bool(_inside(xy[_inside(xy, frame)], inner.padded(r)).any())
    t = coll.get_transform()
    filled = any(c[3] > 0 for c in np.atleast_2d(coll.get_facecolor()))
    shown = Bbox.intersection(inner, frame)
    if shown is None:
        return False
    grid = np.stack(np.meshgrid(np.linspace(shown.x0, shown.x1, 9), np.linspace(shown.y0, shown.y1, 9)), -1)
    for path in coll.get_paths():
        xy = _densify(t.transform(np.asarray(path.vertices, float)), 1.0)
        if _inside(xy[_inside(xy, frame)], inner).any():  # the outline passes under the box
            return True
        if filled and t.transform_path(path).contains_points(grid.reshape(-1, 2)).any():  # the box over the area
            return True
    return False


def legend_covers_data(ax, legend=None, **kwargs) -> list:
    """The data of ``ax`` its legend lies over (see `box_covers_data`).

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        The axes whose data is checked; the figure is drawn first.
    legend : matplotlib.legend.Legend, optional
        Defaults to the legend of ``ax`` (``ValueError`` if it has none).
    **kwargs
        Passed to `box_covers_data`.

    Returns
    -------
    list
        The covered artists; empty when the legend covers nothing.
    """
    leg = _legend_of(ax if legend is None else legend)
    r = draw(ax.figure)
    return box_covers_data(ax, leg.get_window_extent(r), **kwargs)
