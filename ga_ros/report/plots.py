"""PNG plots of the reproduction (matplotlib's object API: no pyplot, no global state)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ga_ros.report.experiments import AerialResult, FutureTracksResult, Table1Result


def _figure(w: float = 8.0, h: float = 4.0):
    from matplotlib.figure import Figure  # lazy: only the report needs matplotlib

    return Figure(figsize=(w, h), dpi=100, layout='constrained')


def plot_fig5(t1: Table1Result, noise_levels, out: Path) -> str:
    """Fig. 5: error along the trajectory at the profile noise level, and MSE versus noise."""
    fig = _figure(10, 7)
    axes = fig.subplots(2, 2)
    for row, kind in enumerate(('lawnmower', 'looping')):
        ax_p, ax_m = axes[row]
        for shape, style in (('open', '-'), ('closed', '--')):
            name = f'{kind}_{shape}'
            if name in t1.profiles:
                prof = t1.profiles[name]
                ax_p.plot(prof['f2f'], ':', label=f'F2F ({shape})')
                ax_p.plot(prof['ga'], style, label=f'GA ({shape})')
            rows = [r for r in t1.rows if r['trajectory'] == name]
            if rows:
                x = [r['noise_pct'] for r in rows]
                ax_m.plot(x, [r['f2f_mse_m2'] for r in rows], ':o', label=f'F2F ({shape})')
                ax_m.plot(x, [r['ga_mse_m2'] for r in rows], style + 'o', label=f'GA ({shape})')
        ax_p.set_title(f'{kind}: position error along the path')
        ax_p.set_xlabel('node (flight order)')
        ax_p.set_ylabel('mean error (m)')
        ax_p.legend(fontsize=8)
        ax_m.set_title(f'{kind}: MSE vs noise')
        ax_m.set_xlabel('noise (% of motion)')
        ax_m.set_ylabel('MSE (m$^2$)')
        ax_m.set_yscale('log')
        ax_m.legend(fontsize=8)
    fig.savefig(out / 'fig5_synthetic.png')
    return 'fig5_synthetic.png'


def plot_fig3(ft: FutureTracksResult, ft_lin: FutureTracksResult, out: Path) -> str:
    """Fig. 2/3: absolute and normalised change of track-1 positions per added track."""
    fig = _figure(10, 4)
    ax_a, ax_n = fig.subplots(1, 2)
    for key in ft.absolute_m:
        ax_a.plot(ft.tracks, ft.absolute_m[key], 'o-', label=f'{key} %')
        ax_n.plot(ft.tracks, ft.normalised[key], 'o-', label=f'se3, {key} %')
    for key in ft_lin.normalised:
        ax_n.plot(ft_lin.tracks, ft_lin.normalised[key], 'x--', label=f'positions only, {key} %')
    ax_a.set_title('Fig. 2: mean change of track-1 positions')
    ax_a.set_ylabel('m')
    ax_n.set_title('Fig. 3: normalised')
    ax_n.set_yscale('log')
    for ax in (ax_a, ax_n):
        ax.set_xlabel('track added (tracks 1..k)')
        ax.legend(fontsize=8)
    fig.savefig(out / 'fig3_future_tracks.png')
    return 'fig3_future_tracks.png'


def plot_fig7(ae: AerialResult, out: Path) -> str:
    """Fig. 7: position error versus frame number, F2F and GA (online window, batch)."""
    fig = _figure(10, 4)
    ax = fig.subplots()
    for key, style in (('f2f', '--'), ('batch', ':')):
        ax.plot(ae.errors[key], style, label=key)
    for key in ae.errors:
        if key.startswith('window_'):
            ax.plot(ae.errors[key], '-', label=key.replace('_', ' '))
    ax.set_yscale('log')
    ax.set_xlabel('frame number')
    ax.set_ylabel('position error (m)')
    ax.set_title('Fig. 7: aerial survey, F2F vs GA')
    ax.legend(fontsize=8)
    fig.savefig(out / 'fig7_aerial_error.png')
    return 'fig7_aerial_error.png'


def plot_fig8(ae: AerialResult, out: Path) -> str | None:
    """Fig. 8: per-window errors before and after the GA at the end of selected tracks."""
    if not ae.fig8:
        return None
    keys = sorted(ae.fig8)
    cols = 3
    rows = int(np.ceil(len(keys) / cols))
    fig = _figure(12, 2.8 * rows)
    axes = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    for ax, k in zip(axes, keys):
        d = ae.fig8[k]
        ax.plot(d['nodes'], d['before'], '-', lw=1, label='before GA')
        ax.plot(d['nodes'], d['after'], '-', lw=2, label='after GA')
        ax.set_title(f'end of track {k}', fontsize=9)
        ax.set_xlabel('frame number', fontsize=8)
        ax.set_ylabel('error (m)', fontsize=8)
    for ax in axes[len(keys):]:
        ax.set_visible(False)
    axes[0].legend(fontsize=8)
    fig.savefig(out / 'fig8_tracks.png')
    return 'fig8_tracks.png'
