"""Section of the wrong-connection table (:mod:`ga_ros.bench.outliers`)."""

from __future__ import annotations

from ga_ros.report.markdown.cells import fixed


def wrong_connections_markdown(w: dict | None) -> str:
    """Section: the wrong-connection table (:mod:`ga_ros.bench.outliers`)."""
    if not w:
        return ''
    L = ['## Wrong cross-track connections (reduced run)\n',
         f'`ga_ros.bench.outliers` on the aerial survey cut to {w["tracks"]} tracks '
         f'({w["nodes"]} nodes, {w["connections"]} connections, {w["cross_connections"]} '
         f'cross-track) at {w["noise_pct"]:g} % noise; a fraction of the cross-track '
         f'connections replaced by gross errors ({w["gross_m"][0]:g}-{w["gross_m"][1]:g} m or '
         f'{w["gross_deg"][0]:g}-{w["gross_deg"][1]:g} deg). Recall: wrong connections '
         'rejected; good rej.: good connections rejected; dATE: change of the aligned ATE '
         'against the clean run of the same family (batch LS; the gated window for `gate`). '
         '`ga-ros bench outliers` runs the larger table of docs/benchmarks.md.\n',
         '| wrong % | method | recall % | precision % | good rej. % | ATE (m) | dATE % '
         '| time (s) |', '|---|---|---|---|---|---|---|---|']
    for x in w['rows']:
        L.append(f'| {x["wrong_pct"]:g} | {x["method"]} | {fixed(x["recall_pct"])} | '
                 f'{fixed(x["precision_pct"])} | {x["good_rejected_pct"]:.2f} | '
                 f'{x["ate_m"]:.3f} | {x["d_ate_pct"]:+.1f} | {x["seconds"]:.1f} |')
    return '\n'.join(L) + '\n'
