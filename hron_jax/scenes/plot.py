"""Top-down matplotlib drawing of a Scene: floors by room type, walls, furniture, slots, doors.

Role: visual sanity check of scenes (and a base layer for trajectory plots). `plot_topdown(scene,
ax)` draws into a matplotlib Axes in world xy metres; `save_topdown(scene, path)` writes a PNG.
"""

from __future__ import annotations

import numpy as np

from . import vocabulary as V

_SLOT_COLOURS = {V.ON_TOP: "tab:orange", V.INSIDE: "tab:purple", V.UNDER: "tab:cyan"}


def _rect(ax, lo, hi, **kw):
    from matplotlib.patches import Rectangle

    ax.add_patch(Rectangle((lo[0], lo[1]), hi[0] - lo[0], hi[1] - lo[1], **kw))


def plot_topdown(scene, ax, labels=True, slots=True, objects=True):
    """Draw the scene into ax (equal aspect); returns ax."""
    c, h = scene.geom_aabb_center, scene.geom_aabb_half
    for r in range(scene.num_rooms):
        cat = V.ROOMS[scene.vocab_index[r]]
        for f in scene.room_floors[r][scene.room_floor_valid[r]]:
            _rect(ax, f[:2], f[2:], facecolor=V.ROOM_RGBA[cat], edgecolor="none", zorder=0)
        if labels:
            big = np.argmax(
                (scene.room_floors[r, :, 2] - scene.room_floors[r, :, 0])
                * (scene.room_floors[r, :, 3] - scene.room_floors[r, :, 1])
                * scene.room_floor_valid[r]
            )
            f = scene.room_floors[r, big]
            area = scene.room_area()[r]
            ax.text(
                (f[0] + f[2]) / 2,
                (f[1] + f[3]) / 2,
                f"{scene.names[r][5:]}\n{area:.1f} m²",
                ha="center",
                va="center",
                fontsize=7,
                color="0.25",
                zorder=6,
                alpha=0.8,
            )
    structure = scene.geom_instance < 0
    for g in np.nonzero(structure)[0]:
        lo, hi = c[g, :2] - h[g, :2], c[g, :2] + h[g, :2]
        low = c[g, 2] - h[g, 2] < 1.0  # lintels above doors are drawn lighter
        _rect(ax, lo, hi, facecolor="0.15" if low else "0.7", edgecolor="none", zorder=3)
    for i in range(scene.num_rooms, scene.num_rooms + scene.num_furniture):
        cat = V.FURNITURE[scene.vocab_index[i]]
        gs = np.nonzero(scene.geom_instance == i)[0]
        for g in gs[np.argsort(c[gs, 2] + h[gs, 2])]:  # higher geoms on top
            _rect(
                ax,
                c[g, :2] - h[g, :2],
                c[g, :2] + h[g, :2],
                facecolor=V.FURNITURE_RGBA[cat][:3],
                edgecolor="k",
                linewidth=0.2,
                alpha=0.9,
                zorder=2,
            )
        if labels:
            ax.text(
                *scene.aabb_center[i, :2],
                scene.names[i].split(":", 1)[1],
                fontsize=4.5,
                ha="center",
                va="center",
                zorder=7,
                color="k",
            )
    if slots:
        for k in range(scene.num_slots):
            col = _SLOT_COLOURS[int(scene.slot_relation[k])]
            lo = scene.slot_center[k, :2] - scene.slot_half[k, :2]
            _rect(
                ax,
                lo,
                lo + 2 * scene.slot_half[k, :2],
                facecolor="none",
                edgecolor=col,
                linewidth=0.5,
                linestyle="--",
                zorder=4,
            )
    for d in range(len(scene.door_names)):
        lo = scene.door_center[d, :2] - scene.door_half[d, :2]
        _rect(
            ax,
            lo,
            lo + 2 * scene.door_half[d, :2],
            facecolor="tab:green",
            alpha=0.35,
            edgecolor="g",
            linewidth=0.5,
            zorder=5,
        )
    if objects:
        for i in range(scene.num_rooms + scene.num_furniture, scene.num_nodes):
            m = scene.mocap_id[i]
            pos = scene.model.body_pos[scene.body_id[i]] if m < 0 else scene.body_pos[i]
            if pos[2] > -1:
                ax.plot(
                    *pos[:2],
                    "o",
                    ms=3,
                    color=V.OBJECT_SHAPES[V.OBJECTS[scene.vocab_index[i]]].rgba[:3],
                    zorder=8,
                )
    for p, yaw in zip(scene.start_pos, scene.start_yaw):
        ax.arrow(p[0], p[1], 0.4 * np.cos(yaw), 0.4 * np.sin(yaw), width=0.05, color="m", zorder=9)
    lo, hi = scene.bounds[0, :2], scene.bounds[1, :2]
    ax.set_xlim(lo[0] - 0.3, hi[0] + 0.3)
    ax.set_ylim(lo[1] - 0.3, hi[1] + 0.3)
    ax.set_aspect("equal")
    return ax


def save_topdown(scene, path, title=None, dpi=150):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo, hi = scene.bounds[0, :2], scene.bounds[1, :2]
    size = hi - lo
    fig, ax = plt.subplots(figsize=(max(4, size[0] * 0.7), max(3, size[1] * 0.7)))
    plot_topdown(scene, ax)
    ax.set_title(title or scene.path, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
