"""Human-readable text of the replay: the ``--info`` listing and the end-of-run summary."""

from __future__ import annotations

from ga_ros.errors import GaError, NoUsableInputError
from ga_ros.eval.metrics import relative_change_text
from ga_ros.io.bag import BagInfo
from ga_ros.io.topic_plan import TopicConfig, TopicPlan
from ga_ros.replay.inputs import InputTopics, plan_inputs
from ga_ros.replay.plan import plan_or_hint
from ga_ros.replay.result import ReplayResult


def info_text(info: BagInfo, config: TopicConfig = TopicConfig(),
              inputs: InputTopics = InputTopics()) -> tuple[str, int]:
    """The topics of a bag and what the replay will use; ``(text, exit status)``: 0 usable, 1
    not with these options, 2 no usable default input (the text then gives the command for the
    bag's topics). ``inputs``: the standard inputs, when given they are the source."""
    lines = [f'bag: {info.path} ({info.storage}, {info.n_messages} messages, '
             f'{info.duration_s:.1f} s)']
    width = max([len(t.name) for t in info.topics] + [5])
    lines.append(f'  {"topic":<{width}}  {"type":<40} count')
    for t in info.topics:
        lines.append(f'  {t.name:<{width}}  {t.msgtype:<40} {t.count}')
    try:
        if inputs.inputs:
            plan = plan_inputs(info, inputs, config.ground_truth)[0]
        else:
            plan = plan_or_hint(info, config)
    except GaError as exc:
        lines.append(f'cannot replay: {exc}')
        return '\n'.join(lines), 2 if isinstance(exc, NoUsableInputError) else 1
    lines.append('will use:')
    lines.extend(f'  {n}' for n in plan_lines(plan))
    return '\n'.join(lines), 0


def plan_lines(plan: TopicPlan) -> list[str]:
    """One line per decision of a topic plan."""
    return list(plan.notes)


def result_text(r: ReplayResult) -> str:
    """End-of-run summary: counts, throughput, errors against ground truth, output files."""
    unit = {'stereo': 'stereo pairs', 'inputs': 'input messages'}.get(r.source,
                                                                      'measurement messages')
    lines = [f'replayed {r.bag}: {r.n_inputs} {unit} -> {r.n_measurements} measurements, '
             f'{r.n_nodes} nodes, {r.n_tracks} tracks, {len(r.updates)} updates '
             f'in {r.seconds:.2f} s ({r.rate:.0f} {unit.split()[-1]}/s)']
    lines += [f'note: {note}' for note in r.notes]
    st = r.source_stats
    if r.source == 'stereo' and st:
        lines.append(f"VO: {st.get('pairs', 0)} pairs, {st.get('keyframes', 0)} keyframes, "
                     f"{st.get('lost', 0)} lost, {st.get('unpaired', 0)} unpaired images; "
                     f"cross-track: {st.get('cross_accepted', 0)} connections accepted of "
                     f"{st.get('cross_attempts', 0)} verified candidates")
        if st.get('reasons'):
            lines.append('pairs without a measurement: ' + ', '.join(
                f'{n} {k}' for k, n in sorted(st['reasons'].items(), key=lambda kv: -kv[1])))
    if r.source == 'inputs' and st:
        for name, v in st.items():
            if isinstance(v, dict) and 'keyframes' in v:
                lines.append(f"{name}: {v['samples']} samples, {v['keyframes']} keyframes, "
                             f"{v['measurements']} measurements, "
                             f"{v['constraints']} external constraints, "
                             f"{v['default_covariances']} default covariances")
            elif isinstance(v, dict) and 'not_covered' in v:
                lines.append(f"{name}: {v['samples']} samples, {v['measurements']} keyframe "
                             f"intervals measured, {v['not_covered']} not covered, "
                             f"{v['pending']} after its last sample, "
                             f"{v['default_covariances']} default covariances")
        cam = st.get('camera')
        if isinstance(cam, dict):
            lines.append(f"camera: {cam['pairs']} pairs, {cam['keyframes_with_image']} keyframes "
                         f"with an image ({cam['keyframes_without_image']} without), "
                         f"{cam['cross_accepted']} cross-track connections accepted of "
                         f"{cam['cross_attempts']} verified candidates")
        warn = st.get('warnings', {})
        if isinstance(warn, dict):  # the end-of-run counts, as the throttled warnings say them
            lines.extend(f'warning: {m}' for m in warn.get('final', []))
    if r.rejected:
        lines.append('rejected: ' + ', '.join(f'{k} {v}' for k, v in sorted(r.rejected.items()))
                     + (f' (e.g. {r.rejected_examples[0]})' if r.rejected_examples else ''))
    if r.failed_updates:
        lines.append(f'failed window updates: {r.failed_updates} (state put back, the track '
                     f'retried in the next update; e.g. {r.failed_update_examples[0]})')
    q = r.quality.get('final')
    if q:
        verdict = 'pass' if q['global_passed'] else 'FAIL'
        lines.append(f'quality (last update): global test {verdict}'
                     f", sigma0^2 {q['sigma0_sq']:.3f}, max |w| {q['w_max']:.2f} on "
                     f"{q['w_max_src_id']}->{q['w_max_dst_id']} (critical {q['w_critical']:.2f}),"
                     f" {q['n_w_rejected']} rejected by the w-test, median MDB "
                     f"{q['mdb_median_m']:.3g} m")
    lines += variance_lines(r.online_variance_components)
    lines += variance_lines(r.variance_components)
    lines += calibration_lines(r.online_calibration, 'online, the last estimate')
    lines += calibration_lines(r.calibration)
    if 'ga' in r.errors:
        lines += error_lines(r)
    if r.ground_truth:
        lines.append(r.ground_truth + ('' if 'ga' in r.errors else
                                       ': no error figures (fewer than 3 nodes matched)'))
    elif 'ga' not in r.errors:
        lines.append('no ground truth (none in the bag, no --ground-truth file): '
                     'no error figures')
    lines += mosaic_lines(r.mosaic)
    lines += map_lines(r.map)
    for w in r.warnings:
        lines.append(f'warning: {w}')
    lines.append('outputs:')
    width = max([len(k) for k in r.files] + [16])
    for k in sorted(r.files):
        lines.append(f'  {k:<{width}} {r.files[k]}')
    return '\n'.join(lines)


def mosaic_lines(mosaic: dict) -> list[str]:
    """The mosaics' seam misregistration (``--mosaic``): per trajectory the median and 95th
    percentile offset between overlapping keyframes of neighbouring tracks, in mosaic pixels."""
    mosaic = {k: v for k, v in mosaic.items() if 'seams' in v}  # not the 'compare' figure
    if not mosaic:
        return []
    first = next(iter(mosaic.values()))
    lines = [f"mosaic seam misregistration (keyframe pairs of neighbouring tracks, mosaic px of "
             f"{first['metres_per_pixel']:.3g} m):"]
    for name, m in mosaic.items():
        s = m['seams']
        lines.append(f"  {name.upper():<7}median {s['median_px']:.2f} px, p95 {s['p95_px']:.2f} "
                     f"px ({s['measured']} pairs; {m['keyframes']} keyframes, "
                     f"{m['covered_area_m2'] / 1e4:.2f} ha)   mosaic_{name}.png")
    return lines


def error_lines(r: ReplayResult) -> list[str]:
    """The errors against ground truth, each row naming its trajectory and file, the compared
    RMSE first (raw when the estimates are anchored at the ground truth, else after each one's
    rigid alignment), GA and the online estimate against F2F in words ("lower" / "higher")."""
    how = r.errors_compared
    head = ('position RMSE' if how == 'raw'
            else 'position RMSE after rigid alignment (each its own; --no-anchor)')
    other = 'after rigid alignment' if how == 'raw' else 'raw, not comparable'
    ga = r.errors['ga']
    f2f = r.errors.get('f2f')
    lines = [f'error vs ground truth ({ga.n} nodes, {head}):']
    rows = [('F2F', 'odometry anchored as GA', 'trajectory_f2f.tum', f2f)]
    if r.final_batch:
        rows += [('online', 'what the live node publishes at the end', 'trajectory_online.tum',
                  r.errors.get('online')),
                 ('GA', 'final batch of everything read', 'trajectory_ga.tum', ga)]
    else:
        rows += [('GA', 'online, no final batch', 'trajectory_ga.tum', ga)]
    for name, what, file, e in rows:
        if e is None:
            continue
        alt = e.ate_aligned if how == 'raw' else e.ate_raw
        text = f'  {name:<7}{e.compared(how):10.3f} m   ({other} {alt:.3f} m)'
        if f2f is not None and name != 'F2F':
            change = relative_change_text(e.compared(how), f2f.compared(how), 'F2F')
            text += f'   {change}' if change else ''
        lines.append(f'{text}   {what}, {file}')
    return lines


def calibration_lines(cal: dict, what: str = 'final batch') -> list[str]:
    """The additional parameters per source of the final batch, or of ``what``
    (:meth:`~ga_ros.core.calibration.CalibrationReport.as_dict`), one line each."""
    params = cal.get('parameters', []) if cal else []
    if not params:
        return []
    camera = ("; extrinsic_rx/ry/rz: a camera extrinsic's rotation error, body frame, rad"
              if any(p['name'].startswith('extrinsic_') for p in params) else '')
    lines = [f"calibration ({what}; test alpha {cal['alpha']:g}; scale: t_true = (1 + k) "
             't_meas; yaw_rate: correction added to the yaw rate, rad/s; time_offset: a '
             f"fix's latency, s; offset_x/y/z: a fix source's offset in map, m{camera}):"]
    for p in params:
        if p['estimated']:
            text = (f"{p['value']:.6g} +- {p['sigma']:.2g} {p['unit']} "
                    f"(|t| {p['test']:.1f})")
        else:
            text = f"not estimated ({p['reason']})"
        lines.append(f"  {p['source']:<12} {p['name']:<11} {text}")
    for f in cal.get('noise', []):
        if f['applied']:
            text = (f"variance factor {f['factor']:.3g} +- {f['sigma']:.2g} applied "
                    f"(stated: v'Pv/r {f['stated_ratio']:.3g}, redundancy "
                    f"{f['redundancy']:.1f})")
        else:
            text = f"stated covariance kept (redundancy {f['redundancy']:.1f})"
        lines.append(f"  {f['source']:<12} {f['part'] + ' noise':<11} {text}")
    return lines


def variance_lines(vc: dict) -> list[str]:
    """The variance factors per source of the final batch or of the online estimate
    (estimated variance / stated variance; the sigmas are off by its square root), one line
    each."""
    groups = {k: v for k, v in vc.items() if not k.startswith('_')}
    if not groups:
        return []
    est = vc.get('_estimation', {})
    if est.get('online'):
        lines = [f"variance components (online, after each track, {est.get('mode', '')}; "
                 'factor = estimated / stated variance):']
    else:
        lines = [f"variance components (final batch, {est.get('iterations', 0)} adjustments"
                 f"{'' if est.get('converged', True) else ', NOT converged'}; factor = "
                 'estimated / stated variance):']
    for name, v in groups.items():
        if v['estimated']:
            text = (f"{v['factor']:.3g} +- {v['sigma']:.2g} ({v['dof']:.0f} dof; sigmas x"
                    f"{v['factor'] ** 0.5:.3g})")
            if not v.get('significant', True):
                text += ', not significant'
            elif not v.get('applied', True):
                text += ', not applied (--variance-components apply)'
        else:
            text = f"not estimated ({v['dof']:.1f} dof), stated covariance used"
        n = v['observations']
        lines.append(f"  {name:<12} {text}, {n} observation{'s' * (n != 1)}")
    return lines


def map_lines(m: dict) -> list[str]:
    """The figures of ``--map`` (``summary.json``'s ``map``): points, covered area, the median
    spread of heights per x-y cell in the map and between the tracks, of the GA and F2F maps
    (empty without maps)."""
    if not m or 'ga' not in m:
        return []
    lines = [f"maps ({m['keyframes_with_cloud']} keyframe clouds, voxel {m['voxel_m']:g} m; "
             f"per {m['ga']['cell_m']:g} m cell: std of the heights, and between tracks the std "
             'of their mean heights; medians):']
    for name in ('f2f', 'ga'):
        f = m[name]
        s, t = f['height_spread_m'], f['track_height_spread_m']
        lines.append(f"  {name.upper():<4}{f['points']:9d} points {f['covered_area_m2']:9.0f} m^2"
                     f"   heights {s['median']:.3f} m   between tracks {t['median']:.3f} m "
                     f"({t['cells']} cells)   map_{name}.ply")
    ratio = m.get('track_height_spread_ga_over_f2f')
    if ratio is not None and ratio == ratio:
        lines.append(f'  between tracks, GA / F2F: {ratio:.2f}')
    return lines
