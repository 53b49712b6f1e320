"""PNG plots of the reproduction (matplotlib's object API: no pyplot, no global state)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ga_ros.report.experiments.future_tracks import FutureTracksResult
from ga_ros.report.experiments.survey import AerialResult, pose_error_profiles
from ga_ros.report.experiments.table1 import Table1Result
from ga_ros.safe_write import save_figure


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
    save_figure(fig, out / 'fig5_synthetic.png')
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
    save_figure(fig, out / 'fig3_future_tracks.png')
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
    save_figure(fig, out / 'fig7_aerial_error.png')
    return 'fig7_aerial_error.png'


def plot_fig8(ae: AerialResult, out: Path, name: str = 'fig8_tracks.png') -> str | None:
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
    save_figure(fig, out / name)
    return name


def plot_fig7_9(vo: AerialResult, syn: AerialResult, out: Path) -> str:
    """Figs. 7 and 9 of experiment 2: position, altitude and heading error along the
    trajectory (F2F, GA online window, batch GA), VO motions (left) beside synthetic noise
    (right)."""
    fig = _figure(12, 9)
    axes = fig.subplots(3, 2)
    for col, (ae, name) in enumerate(((vo, 'VO motions (rendered stereo)'),
                                      (syn, 'synthetic noise'))):
        keys = ['f2f'] + [k for k in ae.paths if k.startswith('window_')] + ['batch']
        for key in keys:
            prof = pose_error_profiles(ae.paths[key], ae.T_true)
            style = '--' if key == 'f2f' else ':' if key == 'batch' else '-'
            label = key.replace('_', ' ').replace('f2f', 'F2F').replace('window', 'GA online')
            label = label.replace('batch', 'GA batch')
            axes[0, col].plot(prof['position'], style, lw=1, label=label)
            axes[1, col].plot(prof['altitude'], style, lw=1, label=label)
            axes[2, col].plot(prof['heading'], style, lw=1, label=label)
        axes[0, col].set_yscale('log')
        axes[0, col].set_title(f'{name}: position error (m)', fontsize=10)
        axes[1, col].set_title('altitude error (m)', fontsize=10)
        axes[2, col].set_title('heading error (rad)', fontsize=10)
        axes[2, col].set_xlabel('frame number (node)')
        axes[0, col].legend(fontsize=8)
    save_figure(fig, out / 'fig7_9_exp2.png')
    return 'fig7_9_exp2.png'


def plot_fig12(registrations, rows: list[dict], images_a, images_b, out: Path) -> str | None:
    """Fig. 12: image ``a``, image ``b`` of the neighbouring swath, ``b`` warped into ``a`` with
    the F2F motion and with the GA motion, and the absolute differences in the overlap."""
    if not registrations:
        return None
    n = len(registrations)
    fig = _figure(15, 2.6 * n)
    axes = np.atleast_2d(fig.subplots(n, 6))
    for i, reg in enumerate(registrations):
        a = images_a[i]
        panels = [(a, f'node {rows[i]["node_a"]} (swath {rows[i]["swath_a"] + 1})'),
                  (images_b[i], f'node {rows[i]["node_b"]} (swath {rows[i]["swath_b"] + 1})')]
        for key, label in (('f2f', 'F2F'), ('window', 'GA')):
            r = reg[key]
            panels.append((r.warped, f'warped, {label}: NCC {r.ncc:.2f}'))
        for key, label in (('f2f', 'F2F'), ('window', 'GA')):
            r = reg[key]
            diff = np.where(r.mask, np.abs(a.astype(float) - r.warped), 0.0)
            panels.append((diff, f'|diff| {label}: {r.mean_abs_diff:.1f}'))
        for ax, (img, title) in zip(axes[i], panels):
            ax.imshow(img, cmap='gray', vmin=0, vmax=255 if img.dtype == np.uint8 else 80)
            ax.set_title(title, fontsize=8)
            ax.set_axis_off()
    save_figure(fig, out / 'fig12_registration.png')
    return 'fig12_registration.png'


def plot_quality(ae: AerialResult, out: Path, name: str = 'fig_quality.png') -> str | None:
    """Quality control of the batch adjustment: histograms of the redundancy numbers, of the
    w-statistics (with the standard normal density) and of the translation MDB, consecutive
    and cross-track connections apart."""
    q, cons = ae.quality, ae.consecutive
    if q is None or cons is None:
        return None
    fig = _figure(13, 3.6)
    ax_r, ax_w, ax_m = fig.subplots(1, 3)
    for sel, label in ((cons, 'consecutive'), (~cons, 'cross-track')):
        if not sel.any():
            continue
        ax_r.hist(q.redundancy_numbers[sel], bins=40, alpha=0.6, label=label)
        w = q.w[sel].ravel()
        ax_w.hist(w[np.isfinite(w) & (w != 0)], bins=80, alpha=0.6, density=True, label=label)
        mdb = q.mdb[sel, :3].ravel()
        ax_m.hist(mdb[np.isfinite(mdb)], bins=60, alpha=0.6, label=label)
    x = np.linspace(-5, 5, 201)
    ax_w.plot(x, np.exp(-0.5 * x ** 2) / np.sqrt(2 * np.pi), 'k-', lw=1, label='N(0, 1)')
    for s in (-1, 1):
        ax_w.axvline(s * q.w_critical, color='r', lw=0.8)
    ax_r.set_title(f'redundancy numbers r_i (sum {q.redundancy_numbers.sum():.0f})', fontsize=9)
    ax_r.set_xlabel('r_i (0: uncontrolled, 6: fully checked)')
    ax_w.set_title(f'w-test (critical {q.w_critical:.2f})', fontsize=9)
    ax_w.set_xlabel('w')
    ax_m.set_title('MDB, translation components', fontsize=9)
    ax_m.set_xlabel('m')
    for ax in (ax_r, ax_w, ax_m):
        ax.legend(fontsize=8)
    save_figure(fig, out / name)
    return name
