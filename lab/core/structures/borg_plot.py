"""A picture of a BORG design model: struts coloured by module type, tags as labelled squares,
the turntable rim with its tags.  Used by `lab structure borg --plot` and for docs/borg.md."""

from __future__ import annotations

import numpy as np

from lab.core.structures.borg import BorgModel

COLOURS = {"deployable": "tab:blue", "closeout_strut": "goldenrod", "closeout_square": "tab:green"}


def plot_borg(model: BorgModel, path: str, views: tuple[tuple[float, float], ...] = ((20, 200), (20, 20))) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(8 * len(views), 8))
    for k, (elev, azim) in enumerate(views, start=1):
        ax = fig.add_subplot(1, len(views), k, projection="3d")
        _draw(ax, model)
        ax.view_init(elev=elev, azim=azim)
        ax.set_title(f"BORG {model.n}x{model.n}x{model.n}, view azimuth {azim} deg")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _draw(ax, model: BorgModel) -> None:
    nodes = model.nodes
    ax.scatter(*nodes.T, s=8, c="pink")
    for m in model.modules:
        for a, b in m.edges:
            p, q = nodes[a], nodes[b]
            ax.plot(*np.c_[p, q], color=COLOURS[m.kind], lw=1.6 if m.kind != "deployable" else 0.9)
    c = np.array([*model.turntable.center_xy_m, 0.0])
    phi = np.linspace(0, 2 * np.pi, 120)
    r = model.turntable.radius_m
    ax.plot(c[0] + r * np.cos(phi), c[1] + r * np.sin(phi), np.zeros_like(phi), color="tab:red", lw=1)
    for t in model.tags.values():
        T = t.structure_T_tag.matrix()
        h = t.size_m / 2
        corners = np.array([[-h, -h, 0, 1], [h, -h, 0, 1], [h, h, 0, 1], [-h, h, 0, 1], [-h, -h, 0, 1]]) @ T.T
        colour = "tab:red" if t.module == "turntable" else "black"
        ax.plot(*corners[:, :3].T, color=colour, lw=1.2)
        n = T[:3, 2] * 0.06
        ax.text(*(T[:3, 3] + n), str(t.id), fontsize=7, color=colour)
    L = model.size_m
    ax.set_xlim(-0.4, L + 0.4)
    ax.set_ylim(-0.4, L + 0.4)
    ax.set_zlim(-0.2, L + 0.2)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_box_aspect((1, 1, (L + 0.4) / (L + 0.8)))
