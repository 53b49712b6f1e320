"""The freeze policies on several noise draws: their table and section."""

from __future__ import annotations

from ga_ros.report.markdown.cells import fixed, interval, signed


def policy_seeds_table(ps: dict) -> list[str]:
    """Markdown lines: the policies over several noise draws (mean +- sd of the gap to batch,
    paired difference with the reference and its interval, verdict), the per-draw gaps and how
    to read them. ``ps`` is :func:`ga_ros.report.experiments.policies.policy_seeds`'s dict (or
    any dict with the keys of :func:`~ga_ros.report.experiments.policies.policy_statistics` plus
    ``draws``)."""
    ref, n = ps['reference'], ps['n']
    level = f'{100 * ps["confidence"]:g} %'
    L = [f'| policy | gap raw %, mean +- sd | gap aligned %, mean +- sd | raw - {ref} (pp), '
         f'mean [{level} CI] | aligned - {ref} (pp), mean [{level} CI] | against {ref} |',
         '|---|---|---|---|---|---|']
    for p, v in ps['policies'].items():
        cells = [f'{signed(v[m]["mean"])} +- {fixed(v[m]["sd"])}' for m in ('raw', 'aligned')]
        vs = v.get('vs_reference')
        if vs is None:
            cells += ['(reference)', '(reference)', '']
        else:
            cells += [interval(vs['raw']), interval(vs['aligned'])]
            worse = [m for m in ('raw', 'aligned') if vs[m]['worse']]
            better = [m for m in ('raw', 'aligned') if vs[m]['better']]
            if n < 2:
                verdict = 'one draw: not testable'
            elif worse:
                verdict = f'**worse** ({", ".join(worse)})'
            elif better:
                verdict = f'better ({", ".join(better)})'
            else:
                verdict = 'no significant difference'
            cells.append(verdict)
        L.append(f'| {p} | ' + ' | '.join(cells) + ' |')
    q = f'{50 + 50 * ps["confidence"]:g} %'
    L += ['', 'How to read it: the sd columns are the spread of a gap from one noise draw to the '
          'next. Within a draw every policy gets the same measurements, so the difference of a '
          f"policy's gap and {ref}'s on that draw (pp: percentage points) is free of what makes "
          f'a draw easy or hard for all of them; its {level} interval is mean -+ t sd / sqrt(n) '
          f"over the n = {n} draws, t the {q} quantile of Student's t with n - 1 degrees of "
          f'freedom. A policy is worse than {ref} when its interval lies entirely above 0, '
          'better when entirely below 0; an interval that contains 0 means that these '
          f'{n} draws cannot tell the two apart (more draws narrow it as 1 / sqrt(n)).', '',
          '| draw r | ' + ' | '.join(f'{p} raw / aligned %' for p in ps['policies']) + ' |',
          '|---|' + '---|' * len(ps['policies'])]
    for i, r in enumerate(ps['draws']):
        L.append(f'| {r} | ' + ' | '.join(
            f'{signed(v["raw"]["values"][i])} / {signed(v["aligned"]["values"][i])}'
            for v in ps['policies'].values()) + ' |')
    return L


def policy_seeds_markdown(r: dict) -> str:
    """Section: the freeze policies on several noise draws (below the single-draw ATE table)."""
    ps = r.get('policy_seeds') or {}
    if not ps.get('available'):
        return ''
    L = [f'### The policies on {ps["n"]} noise draws\n',
         f'The same survey ({ps["tracks"]} double tracks, {ps["noise_pct"]:g} % noise) on '
         f'{ps["n"]} independent noise draws (draw r from `run_rng(seed, 4, r)`; r = 0 is the '
         'table above), each policy run online on every draw and compared with the batch GA of '
         f'the same draw at the end of the survey ({ps["seconds"]:.0f} s; report.json '
         '`policy_seeds`). The target "no policy worse than '
         f'{ps["reference"]}" is met when no interval of the third and fourth columns lies '
         'entirely above 0.\n']
    L += policy_seeds_table(ps)
    return '\n'.join(L) + '\n'
