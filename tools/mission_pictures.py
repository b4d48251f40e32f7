"""The mission report's page: OUT/report/index.html with the summary's tables and three hand-written SVG pictures,
topview.svg (trajectories from above), traffic.svg (paper Fig. 7) and keyframes.svg (paper Fig. 6).

Only the Python standard library. Everything missing (a failed agent, a server that wrote nothing) is skipped and
named on the page. The output depends only on the inputs: same files, same bytes."""

import html
import math
import os

from cvislam_tools.files import load_json, read_csv, read_groundtruth, read_rows
from cvislam_tools.poses import eval_transform, quat_to_matrix

# One colour per agent, by its place in the mission's agent list.
PALETTE = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22",
           "#7f7f7f"]
FONT = "font-family='Helvetica,Arial,sans-serif'"
GT_GREY = "#c8c8c8"
MAX_GT_POINTS = 2000
GAP_S = 0.5  # a longer pause between onboard poses is drawn as a gap


# ---------------------------------------------------------------------------------------------------------------
# Reading the inputs
# ---------------------------------------------------------------------------------------------------------------

def groundtruth_xy(dataset, agent):
    """The agent's ground-truth positions (x, y) from the simulator's EuRoC folder, thinned to MAX_GT_POINTS."""
    rows = read_groundtruth(os.path.join(dataset, agent))
    if not rows:
        return None
    step = max(1, math.ceil(len(rows) / MAX_GT_POINTS))
    return [(p[0], p[1]) for _, p, _ in rows[::step]]


def alignment(evaluation):
    """The SE3 alignment of a cvislam_eval JSON as a function estimate -> ground-truth frame:
    p_gt = s * R(q) * p_est + t (common/eval/report.cpp, S_gt_est); None when it has none, or a zero rotation."""
    try:
        q, t, s = eval_transform(evaluation["se3"]["transform_gt_est"])
        r = quat_to_matrix(*q)
    except (KeyError, TypeError, ValueError):
        return None
    return lambda p: tuple(s * sum(r[i][k] * p[k] for k in range(3)) + t[i] for i in range(3))


def aligned_xy(trajectory_path, evaluation):
    """The TUM trajectory's (t, x, y) mapped onto the ground truth; None if it or its evaluation is missing."""
    transform = alignment(evaluation) if evaluation else None
    rows = read_rows(trajectory_path, None, 4)
    if transform is None or not rows:
        return None
    return [(r[0],) + transform(r[1:4])[:2] for r in rows]


def split_at_gaps(points, gap_s=GAP_S):
    """(t, x, y) points as (x, y) pieces, cut where more than gap_s passes between poses (frames not tracked)."""
    pieces = []
    for i, (t, x, y) in enumerate(points):
        if i == 0 or t - points[i - 1][0] > gap_s:
            pieces.append([])
        pieces[-1].append((x, y))
    return pieces


# ---------------------------------------------------------------------------------------------------------------
# SVG helpers
# ---------------------------------------------------------------------------------------------------------------

def nice_step(span, target=6):
    """A round tick step (1, 2 or 5 times a power of ten) giving about `target` ticks over span."""
    raw = max(span, 1e-12) / target
    p = 10 ** math.floor(math.log10(raw))
    return next(m * p for m in (1, 2, 5, 10) if m * p >= raw)


def ticks(lo, hi, step):
    """The multiples of step within [lo, hi]."""
    first = math.ceil(lo / step - 1e-9)
    return [k * step for k in range(first, math.floor(hi / step + 1e-9) + 1)]


def tick_text(value, step):
    """A tick label with as many decimals as the step needs."""
    decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    text = f"{value:.{decimals}f}"
    return "0" if float(text) == 0 else text


def esc(text):
    """Text escaped for SVG or HTML."""
    return html.escape(str(text), quote=True)


def svg_document(width, height, body, title):
    """A standalone SVG document around body (a list of elements)."""
    return (f"<svg xmlns='http://www.w3.org/2000/svg' width='{width}' height='{height}' "
            f"viewBox='0 0 {width} {height}' {FONT} font-size='12'>\n<title>{esc(title)}</title>\n"
            f"<rect width='{width}' height='{height}' fill='white'/>\n" + "\n".join(body) + "\n</svg>\n")


def placeholder(title, text, width=680, height=120):
    """An SVG that says why there is no picture."""
    return svg_document(width, height, [f"<text x='20' y='30' font-size='14' font-weight='bold'>{esc(title)}</text>",
                                        f"<text x='20' y='60' fill='#a00'>{esc(text)}</text>"], title)


class Frame:
    """A plot area of (left, top, width, height) pixels showing data x in xr and y in yr (y grows upwards)."""

    def __init__(self, left, top, width, height, xr, yr):
        self.left, self.top, self.width, self.height = left, top, width, height
        self.xr, self.yr = xr, yr

    def px(self, x, y):
        """Pixel position of a data point."""
        fx = (x - self.xr[0]) / (self.xr[1] - self.xr[0])
        fy = (y - self.yr[0]) / (self.yr[1] - self.yr[0])
        return self.left + fx * self.width, self.top + (1 - fy) * self.height

    def axes(self, xstep, ystep, xlabel, ylabel):
        """Light grid, tick labels, a frame and the axis labels."""
        out = []
        for x in ticks(self.xr[0], self.xr[1], xstep):
            px, _ = self.px(x, 0)
            out.append(f"<line x1='{px:.1f}' y1='{self.top}' x2='{px:.1f}' y2='{self.top + self.height}' "
                       f"stroke='#eee'/>")
            out.append(f"<text x='{px:.1f}' y='{self.top + self.height + 15}' text-anchor='middle' "
                       f"fill='#444'>{tick_text(x, xstep)}</text>")
        for y in ticks(self.yr[0], self.yr[1], ystep):
            _, py = self.px(0, y)
            out.append(f"<line x1='{self.left}' y1='{py:.1f}' x2='{self.left + self.width}' y2='{py:.1f}' "
                       f"stroke='#eee'/>")
            out.append(f"<text x='{self.left - 6}' y='{py + 4:.1f}' text-anchor='end' fill='#444'>"
                       f"{tick_text(y, ystep)}</text>")
        out.append(f"<rect x='{self.left}' y='{self.top}' width='{self.width}' height='{self.height}' fill='none' "
                   f"stroke='#888'/>")
        if xlabel:
            out.append(f"<text x='{self.left + self.width / 2:.1f}' y='{self.top + self.height + 34}' "
                       f"text-anchor='middle'>{esc(xlabel)}</text>")
        cy = self.top + self.height / 2
        out.append(f"<text x='{self.left - 48}' y='{cy:.1f}' text-anchor='middle' "
                   f"transform='rotate(-90 {self.left - 48} {cy:.1f})'>{esc(ylabel)}</text>")
        return out

    def polyline(self, points, colour, width=1.5, extra=""):
        """A line through data points."""
        coords = " ".join("{:.1f},{:.1f}".format(*self.px(x, y)) for x, y in points)
        return (f"<polyline points='{coords}' fill='none' stroke='{colour}' stroke-width='{width}' "
                f"stroke-linejoin='round' {extra}/>")


def legend(items, x, y, width):
    """Legend entries (label, swatch kind, colour) flowing left to right from (x, y) within width pixels;
    kinds: 'line', 'thin', 'thick', 'dot'. Returns (elements, height used)."""
    out, cx, cy = [], x, y
    for label, kind, colour in items:
        w = 34 + 7 * len(label)
        if cx + w > x + width and cx > x:
            cx, cy = x, cy + 20
        if kind == "dot":
            out.append(f"<circle cx='{cx + 11}' cy='{cy - 4}' r='3' fill='{colour}' stroke='white' "
                       f"stroke-width='0.8'/>")
        else:
            sw = {"thin": 1.2, "thick": 4, "line": 2.5}[kind]
            out.append(f"<line x1='{cx}' y1='{cy - 4}' x2='{cx + 22}' y2='{cy - 4}' stroke='{colour}' "
                       f"stroke-width='{sw}'/>")
        out.append(f"<text x='{cx + 28}' y='{cy}'>{esc(label)}</text>")
        cx += w
    return out, cy - y + 20


def colour_of(agents, agent):
    """The agent's colour, by its place in the mission's agent list."""
    return PALETTE[(agents.index(agent) if agent in agents else len(agents)) % len(PALETTE)]


# ---------------------------------------------------------------------------------------------------------------
# The three pictures
# ---------------------------------------------------------------------------------------------------------------

def evaluation(out, summary, agent, which):
    """eval/<which>_<agent>.json, if this report evaluated it (the summary has its ATE; an older file left by an
    earlier report is not used)."""
    row = next((r for r in summary.get("agents") or [] if r.get("agent") == agent), {})
    evaluated = row.get(f"{which}_ate_se3_m") is not None
    return load_json(os.path.join(out, "eval", f"{which}_{agent}.json")) if evaluated else None


def topview_svg(out, summary, notes):
    """Top view (x-y, metres, equal aspect) of every agent: ground truth in grey, the onboard trajectory (aligned
    with its SE3 evaluation) as a thin line, the server's keyframes of it (aligned with the server evaluation's
    own transform) as dots. Missing pieces are appended to notes."""
    mission = summary.get("mission") or {}
    agents, name = mission.get("agents", []), mission.get("mission", "")
    layers = []  # (agent, ground truth, onboard pieces, server keyframes)
    for a in agents:
        gt = groundtruth_xy(mission.get("dataset", ""), a)
        onboard = aligned_xy(os.path.join(out, "agents", a, "trajectory.txt"), evaluation(out, summary, a, "onboard"))
        server = aligned_xy(os.path.join(out, "server", name, f"keyframes_agent{a.replace('agent', '')}.txt"),
                            evaluation(out, summary, a, "server"))
        for what, value in (("ground truth", gt), ("onboard trajectory or its evaluation", onboard),
                            ("server keyframes or their evaluation", server)):
            if not value:
                notes.append(f"top view: {a}: {what} missing, not drawn")
        layers.append((a, gt or [], split_at_gaps(onboard or []), [p[1:] for p in server or []]))
    points = [p for _, gt, onboard, server in layers for p in gt + server + sum(onboard, [])]
    if not points:
        return placeholder("Top view", "nothing to draw: no ground truth and no trajectories")

    # Equal aspect: one scale for both axes, the plot area shaped like the data (within limits).
    xs, ys = [p[0] for p in points], [p[1] for p in points]
    span = max(max(xs) - min(xs), max(ys) - min(ys), 0.1)
    pad = 0.04 * span
    xr, yr = [min(xs) - pad, max(xs) + pad], [min(ys) - pad, max(ys) + pad]
    scale = min(600 / (xr[1] - xr[0]), 600 / (yr[1] - yr[0]))
    for r, minimum in ((xr, 360), (yr, 240)):  # widen a thin range around its middle
        extra = max(0.0, minimum / scale - (r[1] - r[0])) / 2
        r[0], r[1] = r[0] - extra, r[1] + extra
    left, top = 64, 40
    frame = Frame(left, top, (xr[1] - xr[0]) * scale, (yr[1] - yr[0]) * scale, xr, yr)
    width = int(left + frame.width + 20)
    step = nice_step(max(xr[1] - xr[0], yr[1] - yr[0]), 8)
    body = [f"<text x='{left}' y='22' font-size='14' font-weight='bold'>Top view of mission "
            f"{esc(name)} (simulated), x-y plane</text>"]
    body += frame.axes(step, step, "x [m]", "y [m]")
    for a, gt, _, _ in layers:
        if gt:
            body.append(frame.polyline(gt, GT_GREY, 4, "stroke-linecap='round'"))
    for a, _, onboard, _ in layers:  # a lone pose between gaps as a small cross
        colour = colour_of(agents, a)
        for piece in onboard:
            if len(piece) > 1:
                body.append(frame.polyline(piece, colour, 1.2))
            else:
                px, py = frame.px(*piece[0])
                body.append(f"<path d='M{px - 3:.1f},{py - 3:.1f}l6,6m0,-6l-6,6' stroke='{colour}' "
                            f"stroke-width='1.2'/>")
    for a, gt, _, server in layers:
        colour = colour_of(agents, a)
        body += [f"<circle cx='{px:.1f}' cy='{py:.1f}' r='3' fill='{colour}' stroke='white' stroke-width='0.8'/>"
                 for px, py in (frame.px(x, y) for x, y in server)]
        if gt:  # the agent's name at its start
            px, py = frame.px(*gt[0])
            body.append(f"<circle cx='{px:.1f}' cy='{py:.1f}' r='4.5' fill='none' stroke='{colour}' "
                        f"stroke-width='1.5'/><text x='{px + 7:.1f}' y='{py - 7:.1f}' fill='{colour}' "
                        f"font-weight='bold'>{esc(a)}</text>")
    items = [(a, "line", colour_of(agents, a)) for a, *_ in layers]
    items += [("ground truth", "thick", GT_GREY), ("onboard, every frame (SE3-aligned)", "thin", "#333"),
              ("server keyframes (SE3-aligned by the server evaluation)", "dot", "#333")]
    y0 = top + frame.height + 58
    elements, used = legend(items, left, y0, width - left - 10)
    return svg_document(width, int(y0 + used), body + elements, f"Top view of mission {name}")


def rate_series(rows, column):
    """Rates in kB/s between consecutive samples of a cumulative byte counter, as step-line points."""
    points = []
    for prev, cur in zip(rows, rows[1:]):
        dt = cur[0] - prev[0]
        if dt > 0:
            rate = (cur[column] - prev[column]) / dt / 1000
            points += [(prev[0], rate), (cur[0], rate)]
    return points


def link_samples(out, agent):
    """The agent's (t_s, up_bytes, down_bytes) samples from link_timeline.csv, closed with link.json's totals at
    the link's end (the timeline samples once a second and misses what was sent after its last sample)."""
    rows = read_csv(os.path.join(out, "agents", agent, "link_timeline.csv"))
    if not rows:
        return None
    try:
        samples = [(float(r["t_s"]), float(r["up_bytes"]), float(r["down_bytes"])) for r in rows]
    except (KeyError, ValueError):
        return None
    link = load_json(os.path.join(out, "agents", agent, "link.json"))
    try:
        end = (float(link["duration_s"]), float(link["up"]["message"]["bytes"]),
               float(link["down"]["message"]["bytes"]))
        if end[0] > samples[-1][0]:
            samples.append(end)
    except (KeyError, TypeError, ValueError):
        pass
    return samples


def traffic_svg(out, mission, notes):
    """Paper Fig. 7: each agent's up and down rate in kB/s over the link's wall time, two stacked panels."""
    agents = mission.get("agents", [])
    series = {}
    for a in agents:
        samples = link_samples(out, a)
        if samples is None or len(samples) < 2:
            notes.append(f"traffic: {a}: no link_timeline.csv, not drawn")
            continue
        series[a] = {"up": rate_series(samples, 1), "down": rate_series(samples, 2)}
    if not series:
        return placeholder("Traffic", "nothing to draw: no agent wrote link_timeline.csv")
    t_max = max(p[0] for s in series.values() for p in s["up"] + s["down"])
    xstep = nice_step(t_max, 10)
    xr = [0.0, math.ceil(t_max / xstep - 1e-9) * xstep]
    left, width, height, body = 70, 590, 170, []
    body.append(f"<text x='{left}' y='22' font-size='14' font-weight='bold'>Traffic per agent and direction "
                f"(agent side)</text>")
    for i, direction in enumerate(("up", "down")):
        top = 48 + i * (height + 48)
        y_max = 1.05 * max([p[1] for s in series.values() for p in s[direction]] + [0.0])  # headroom
        ystep = nice_step(y_max or 1.0, 4)
        frame = Frame(left, top, width, height, xr, [0.0, math.ceil((y_max or 1.0) / ystep - 1e-9) * ystep])
        body += frame.axes(xstep, ystep, "wall time since the agent's link opened [s]" if i else "",
                           f"{direction} [kB/s]")
        body.append(f"<text x='{left + width}' y='{top - 6}' text-anchor='end' font-weight='bold' fill='#444'>"
                    f"{'uplink: agent to server' if direction == 'up' else 'downlink: server to agent'}</text>")
        for a, s in series.items():
            if s[direction]:
                body.append(frame.polyline(s[direction], colour_of(agents, a), 1.8, "stroke-opacity='0.85'"))
    y0 = 48 + 2 * (height + 48) + 6
    elements, used = legend([(a, "line", colour_of(agents, a)) for a in series], left, y0, width)
    return svg_document(left + width + 20, int(y0 + used), body + elements, "Traffic per agent and direction")


def keyframes_svg(out, mission, notes):
    """Paper Fig. 6: keyframes the server holds over time, per agent and in total (the mission's rows of
    server/timeline.csv)."""
    agents, name = mission.get("agents", []), mission.get("mission", "")
    rows = read_csv(os.path.join(out, "server", "timeline.csv"))
    if not rows:
        notes.append("keyframes: server/timeline.csv missing or empty, not drawn")
        return placeholder("Keyframes on the server", "nothing to draw: the server wrote no timeline.csv")
    per_agent, totals = {}, {}
    for r in rows:
        if r.get("mission") != name:
            continue
        try:
            t, agent, kfs = float(r["t_s"]), f"agent{int(r['agent'])}", int(r["keyframes"])
        except (KeyError, ValueError):
            continue
        per_agent.setdefault(agent, []).append((t, kfs))
        totals[t] = totals.get(t, 0) + kfs
    if not per_agent:
        notes.append(f"keyframes: server/timeline.csv has no rows of mission {name}, not drawn")
        return placeholder("Keyframes on the server", f"nothing to draw: no rows of mission {name}")
    for a in agents:
        if a not in per_agent:
            notes.append(f"keyframes: the server's timeline has no rows of {a}")
    total = sorted(totals.items())
    t_max, k_max = max(t for t, _ in total), 1.05 * max(k for _, k in total)  # headroom above the top line
    xstep, ystep = nice_step(t_max, 10), nice_step(max(k_max, 1), 5)
    frame = Frame(70, 40, 500, 230, [0.0, math.ceil(t_max / xstep - 1e-9) * xstep],
                  [0.0, math.ceil(max(k_max, 1) / ystep - 1e-9) * ystep])
    body = [f"<text x='70' y='22' font-size='14' font-weight='bold'>Keyframes held by the server, mission "
            f"{esc(name)}</text>"]
    body += frame.axes(xstep, ystep, "server wall time [s]", "keyframes")
    body.append(frame.polyline(total, "#222", 2.5))
    order = sorted(per_agent, key=lambda a: (agents.index(a) if a in agents else len(agents), a))
    for a in order:
        body.append(frame.polyline(per_agent[a], colour_of(agents, a), 1.8, "stroke-opacity='0.85'"))
    elements, used = legend([("total", "line", "#222")] + [(a, "line", colour_of(agents, a)) for a in order],
                            70, 332, 500)
    return svg_document(590, int(332 + used), body + elements, "Keyframes held by the server")


# ---------------------------------------------------------------------------------------------------------------
# The page
# ---------------------------------------------------------------------------------------------------------------

# A keyframe's way from the camera to the server and back, in the order the waterfall draws it (the names of
# cvislam_trace's links; the ones beside this path, such as local BA, stay in its table).
WAY = ["frame captured -> keyframe decided", "keyframe decided -> batch sent", "batch sent -> stored on the server",
       "stored -> place recognition queried", "queried -> matched and merged (or loop closed)",
       "merged -> optimised by the GBA", "optimised -> corrections applied by the agent"]


def waterfall_svg(out):
    """A keyframe's way as a waterfall: each link of trace/chain.json (cvislam_trace merge) a bar of its p50 that
    starts where the link before it ended, with a whisker to its p99. None without a traced mission."""
    chain = load_json(os.path.join(out, "trace", "chain.json"))
    if not chain:
        return None
    links = {link["link"]: link for link in chain.get("links", [])}
    rows = [links[name] for name in WAY if name in links and links[name]["n"] > 0]
    if not rows:
        return placeholder("A keyframe's way", "nothing to draw: no link of the chain has a sample")
    ends, t = [], 0.0
    for r in rows:
        ends.append((t, t + r["p50_ms"], t + r["p99_ms"]))
        t += r["p50_ms"]
    t_max = max(e for _, _, e in ends) * 1.05
    xstep = nice_step(t_max, 8)
    row_h, top, label_w, plot_w = 30, 40, 360, 420
    frame = Frame(label_w, top, plot_w, row_h * len(rows), [0.0, math.ceil(t_max / xstep - 1e-9) * xstep],
                  [0.0, float(len(rows))])
    body = ["<text x='10' y='22' font-size='14' font-weight='bold'>A keyframe's way (p50 bars one after "
            "another, whiskers to p99)</text>"]
    bottom = top + row_h * len(rows)
    for x in ticks(frame.xr[0], frame.xr[1], xstep):
        px, _ = frame.px(x, 0)
        body.append(f"<line x1='{px:.1f}' y1='{top}' x2='{px:.1f}' y2='{bottom}' stroke='#eee'/>")
        body.append(f"<text x='{px:.1f}' y='{bottom + 15}' text-anchor='middle' fill='#444'>{tick_text(x, xstep)}"
                    f"</text>")
    body.append(f"<text x='{label_w + plot_w / 2:.1f}' y='{bottom + 34}' text-anchor='middle'>time since the "
                f"frame was captured [ms]</text>")
    for i, (r, (start, p50_end, p99_end)) in enumerate(zip(rows, ends)):
        y = top + i * row_h
        x0, _ = frame.px(start, 0)
        x1, _ = frame.px(p50_end, 0)
        x2, _ = frame.px(p99_end, 0)
        body.append(f"<text x='{label_w - 8}' y='{y + 19}' text-anchor='end' font-size='11'>{esc(r['link'])} "
                    f"(n {r['n']})</text>")
        body.append(f"<rect x='{x0:.1f}' y='{y + 7}' width='{max(x1 - x0, 1.5):.1f}' height='{row_h - 14}' "
                    f"fill='#4a7bb7'/>")
        body.append(f"<line x1='{x1:.1f}' y1='{y + row_h / 2:.1f}' x2='{x2:.1f}' y2='{y + row_h / 2:.1f}' "
                    f"stroke='#4a7bb7'/>")
        body.append(f"<text x='{x2 + 4:.1f}' y='{y + 19}' font-size='10' fill='#444'>{r['p50_ms']:.0f} / "
                    f"{r['p99_ms']:.0f}</text>")
    return svg_document(label_w + plot_w + 80, top + row_h * len(rows) + 50, body, "A keyframe's way")


def num(value, fmt, scale=1.0):
    """value * scale formatted, or 'n/a' for None, NaN or anything not a number."""
    try:
        v = float(value) * scale
    except (TypeError, ValueError):
        return "n/a"
    return "n/a" if math.isnan(v) else format(v, fmt)


def table(header, rows, caption="", text_columns=1):
    """An HTML table; cells are escaped, the first text_columns left-aligned, the numbers after them right-aligned."""
    head = "".join(f"<th class='t'>{esc(h)}</th>" if i < text_columns else f"<th>{esc(h)}</th>"
                   for i, h in enumerate(header))
    body = "".join("<tr>" + "".join(f"<td class='t'>{esc(c)}</td>" if i < text_columns else f"<td>{esc(c)}</td>"
                                    for i, c in enumerate(row)) + "</tr>\n" for row in rows)
    if not rows:
        body = f"<tr><td class='t' colspan='{len(header)}'>nothing recorded</td></tr>"
    cap = f"<caption>{esc(caption)}</caption>" if caption else ""
    return f"<table>{cap}<thead><tr>{head}</tr></thead><tbody>\n{body}</tbody></table>\n"


def accuracy_html(summary):
    """Accuracy per agent and the joint line: (the table, notes on it)."""
    rows = [[r.get("agent"), num(r.get("frames"), ".0f"),
             num(r.get("onboard_ate_se3_m"), ".2f", 100), num(r.get("live_ate_se3_m"), ".2f", 100),
             num(r.get("onboard_ate_sim3_m"), ".2f", 100), num(r.get("onboard_scale_error_percent"), "+.2f"), num(r.get("server_keyframes"), ".0f"),
             num(r.get("server_ate_se3_m"), ".2f", 100), num(r.get("server_ate_sim3_m"), ".2f", 100),
             num(r.get("server_scale_error_percent"), "+.2f"), num(r.get("server_maps"), ".0f")]
            for r in summary.get("agents") or []]
    joint = summary.get("joint")
    if joint:
        rows.append(["joint (server)", "", "", "", "", "", num(joint.get("poses"), ".0f"),
                     num(joint.get("ate_se3_m"), ".2f", 100), num(joint.get("ate_sim3_m"), ".2f", 100), "", ""])
    header = ["agent", "frames", "onboard ATE SE3 [cm]", "live ATE SE3 [cm]", "onboard ATE Sim3 [cm]",
              "onboard scale err [%]",
              "server KFs", "server ATE SE3 [cm]", "server ATE Sim3 [cm]", "server scale err [%]", "server maps"]
    text = ""
    if joint:
        text += ("<p class='note'>joint: the server keyframes of all agents against their ground truth; each server "
                 "map is aligned on its own (the maps are not fused yet) and the errors pooled"
                 f" (alignment '{esc(joint.get('align', 'each'))}').</p>")
    else:
        text += "<p class='note'>joint: not evaluated (no server keyframes were written).</p>"
    several = [r.get("agent") for r in summary.get("agents") or [] if (r.get("server_maps") or 0) > 1]
    if several:
        text += (f"<p class='warn'>{esc(', '.join(several))}: the server holds several maps of it; its keyframes "
                 "file mixes their frames and the server ATE aligns them with one transform.</p>")
    return table(header, rows, "ATE after SE3 alignment (Sim3 beside it); scale error from the Sim3 alignment"), text


def traffic_html(summary):
    """Traffic per agent (per second of sensor time, as the printed table)."""
    rows = []
    for r in summary.get("traffic") or []:
        sensor = r.get("sensor_s", (summary.get("mission") or {}).get("duration_s"))
        rows.append([r.get("agent"), num(sensor, ".1f"), num(r.get("wall_s", r.get("duration_s")), ".1f"),
                     num(r.get("up_bytes"), ".2f", 1e-6), num(r.get("up_mb_per_s"), ".3f"),
                     num(r.get("down_bytes"), ".2f", 1e-3), num(r.get("down_mb_per_s"), ".4f", 1000),
                     num(r.get("batches"), ".0f"), num(r.get("reconnects"), ".0f"),
                     num(r.get("keyframes_unacknowledged"), ".0f")])
    header = ["agent", "sensor time [s]", "link wall time [s]", "up [MB]", "up [MB/s]", "down [kB]",
              "down [kB/s]", "batches", "reconnects", "unacked KFs"]
    return table(header, rows, "Agent side, rates per second of sensor time (paper Table IV: up 0.12-0.15 MB/s, "
                               "down about 0.7 MB/s)")


def messages_html(summary):
    """Messages by kind: what the server counted, beside what the agents counted."""
    messages = summary.get("messages") or {}
    agent_side = messages.get("agent_side") or {}
    rows = []
    for direction in ("up", "down"):
        for kind, c in (messages.get(direction) or {}).items():
            mine = (agent_side.get(direction) or {}).get(kind)
            rows.append([direction, kind, num(c.get("count"), ".0f"), num(c.get("bytes"), ".0f"),
                         num(c.get("bytes_each"), ".1f") if c.get("bytes") else "",
                         num(mine[1], ".0f") if mine else "n/a"])
    return table(["direction", "kind", "count", "bytes", "bytes each", "agents' count [bytes]"], rows,
                 "All agents, as the server received them; sizes are serialized bytes", 2)


def stages_html(summary):
    """Agent stage timings p50 / p99."""
    stages = ["orb_extraction", "matching", "pose_optimisation", "motion_ba", "tracking_total", "local_ba",
              "mapping_total"]
    rows = [[a] + [f"{num(s[k].get('p50_ms'), '.1f')} / {num(s[k].get('p99_ms'), '.1f')}" if k in s else "n/a"
                   for k in stages] for a, s in (summary.get("stages") or {}).items()]
    return table(["agent"] + [s.replace("_", " ") for s in stages], rows,
                 "p50 / p99 [ms] with the link on; all agents and the server share this machine's cores")


def real_data_html(out, summary):
    """The real-data line: the EuRoC V1_01 excerpt, one agent through the same server."""
    r = summary.get("real_data")
    if not r:
        return "<p class='note'>No real-data run in this mission (skipped, or its agent wrote nothing).</p>"
    evaluation = load_json(os.path.join(out, "eval", "onboard_real_v101.json")) or {}
    path = evaluation.get("groundtruth_path_m")
    rows = [[num(r.get("frames"), ".0f"), num(r.get("onboard_ate_se3_m"), ".2f", 1000),
             num(r.get("live_ate_se3_m"), ".2f", 1000), num(r.get("server_keyframes"), ".0f"), num(r.get("server_ate_se3_m"), ".2f", 1000),
             num(r.get("up_bytes"), ".2f", 1e-6), num(path, ".1f", 100)]]
    text = table(["frames", "onboard ATE SE3 [mm]", "live ATE SE3 [mm]", "server KFs", "server ATE SE3 [mm]", "up [MB]",
                  "ground-truth path [cm]"], rows)
    if path is not None and path < 0.5:
        text += (f"<p class='warn'>The ground truth moves only {num(path, '.1f', 100)} cm over the excerpt: the "
                 "ATE says little about tracking quality.</p>")
    return text


CSS = """
body { font-family: Helvetica, Arial, sans-serif; margin: 24px; color: #222; max-width: 1500px; }
h1 { margin-bottom: 4px; } h2 { margin-top: 32px; border-bottom: 1px solid #ddd; padding-bottom: 4px; }
.banner { background: #fff4d6; border: 1px solid #e0c060; padding: 8px 12px; margin: 12px 0; }
.row { display: flex; flex-wrap: wrap; gap: 28px; align-items: flex-start; }
table { border-collapse: collapse; font-size: 13px; margin: 8px 0; }
caption { caption-side: top; text-align: left; color: #555; padding-bottom: 4px; font-size: 12px; }
th, td { border: 1px solid #ddd; padding: 3px 8px; }
th { background: #f3f3f3; font-weight: 600; }
td, th { text-align: right; font-variant-numeric: tabular-nums; }
td.t, th.t { text-align: left; }
tr:last-child td { border-bottom: 1px solid #bbb; }
.note { color: #555; font-size: 12px; max-width: 760px; }
.side { width: 400px; }
.warn { color: #8a4b00; font-size: 12px; max-width: 760px; }
ul.missing { color: #a00; font-size: 13px; }
figure { margin: 0; } figure svg { max-width: 100%; height: auto; border: 1px solid #eee; }
"""


def write_report(out, summary):
    """Write OUT/report/topview.svg, traffic.svg, keyframes.svg and index.html (the pictures inline)."""
    report = os.path.join(out, "report")
    os.makedirs(report, exist_ok=True)
    mission = summary.get("mission") or {}
    notes = []
    pictures = {"topview": topview_svg(out, summary, notes), "traffic": traffic_svg(out, mission, notes),
                "keyframes": keyframes_svg(out, mission, notes)}
    waterfall = waterfall_svg(out)
    if waterfall is not None:
        pictures["waterfall"] = waterfall
    for name, svg in pictures.items():
        with open(os.path.join(report, f"{name}.svg"), "w") as f:
            f.write(svg)
    for row in summary.get("agents") or []:
        if not row.get("frames"):
            notes.append(f"{row.get('agent')}: no onboard trajectory was evaluated (did the agent fail?)")
    for a in mission.get("agents", []):
        if a not in (summary.get("stages") or {}):
            notes.append(f"{a}: no latency.json, no stage timings")
        if a not in [r.get("agent") for r in summary.get("traffic") or []]:
            notes.append(f"{a}: no link.json, no traffic row")

    def figure(name):
        """The picture inline (its file beside this page holds the same SVG)."""
        svg = pictures[name]
        return f"<figure>{svg[svg.index('<svg'):]}<figcaption class='note'>{name}.svg</figcaption></figure>"

    wall = mission.get("wall_s") or {}
    params = [["preset", mission.get("preset", "n/a")], ["seed", mission.get("seed", "n/a")],
              ["duration per agent [s]", mission.get("duration_s", "n/a")],
              ["mode", f"{mission.get('mode', 'n/a')}-inertial"], ["pace", mission.get("pace", "n/a")],
              ["agents", ", ".join(mission.get("agents", [])) or "none"],
              ["simulated dataset", mission.get("dataset", "n/a")],
              ["wall time [s]", ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in wall.items()) or "n/a"]]
    name = mission.get("mission", "?")
    parts = [
        "<!doctype html>\n<html lang='en'><head><meta charset='utf-8'>",
        f"<title>cvislam mission {esc(name)}</title><style>{CSS}</style></head><body>",
        f"<h1>cvislam mission {esc(name)}</h1>",
        "<div class='banner'><b>Simulated data.</b> Every figure on this page comes from the project's own "
        "SIMULATOR (cvislam_sim: rendered images, synthetic IMU and ground truth), not from EuRoC, except the "
        "<a href='#real'>real-data section</a> at the end.</div>",
        "<div class='row'>", table(["parameter", "value"], params, text_columns=2),
        "</div>"]
    if notes:
        parts.append("<h2>Missing or skipped</h2><ul class='missing'>"
                     + "".join(f"<li>{esc(n)}</li>" for n in notes) + "</ul>")
    accuracy, accuracy_notes = accuracy_html(summary)
    parts += [
        "<h2>Accuracy</h2>", accuracy,
        "<div class='row'>", figure("topview"), "<div class='side'>", accuracy_notes,
        "<p class='note'>Top view: grey, each agent's ground truth; thin line, the agent's onboard trajectory "
        "(every frame) moved onto the ground truth with the SE3 alignment of its own evaluation "
        "(eval/onboard_agentN.json); dots, the keyframes the server holds of the agent, aligned with the server "
        "evaluation's transform (eval/server_agentN.json). Gaps in the thin line: more than 0.5 s without a "
        "tracked frame; a cross, a lone pose between gaps. The circle marks each agent's start. The real-data "
        "run is a separate mission and is not drawn.</p></div></div>",
        "<h2>Traffic</h2>", traffic_html(summary),
        "<div class='row'>", figure("traffic"),
        "<p class='note side'>Paper Fig. 7. Rates are differences of the cumulative byte counters the agent "
        "samples about once a second (agents/agentN/link_timeline.csv), drawn as steps over each interval; the "
        "last step ends at the link's close with link.json's totals. Time is wall time, so a sync-paced run can "
        "be shorter than its sensor time.</p></div>",
        "<h2>Server: keyframes held and messages received</h2>",
        "<div class='row'>", figure("keyframes"), "<div>", messages_html(summary),
        "<p class='note side'>Keyframes (paper Fig. 6): what the server holds of each agent and in total, from "
        "server/timeline.csv (one row per agent per second; this mission's rows only).</p></div></div>",
        "<h2>Agent stage timings</h2>", stages_html(summary)]
    if "waterfall" in pictures:
        parts += [
            "<h2>A keyframe's way from the camera to the server and back</h2>", "<div class='row'>",
            figure("waterfall"),
            "<p class='note side'>From the traces of the server and the agents (--trace), joined on the server's "
            "clock by cvislam_trace (trace/chain.txt has every link and the clock offsets). Each bar is a link's "
            "p50 over the keyframes that went through it, drawn after the link before it; the line runs to its "
            "p99. Only keyframes whose query found a match go beyond the place-recognition query. Open "
            "trace/mission_trace.json in https://ui.perfetto.dev to see every span.</p></div>"]
    parts += [
        "<h2 id='real'>Real data: EuRoC V1_01 excerpt</h2>",
        "<p class='note'>Real images: the first 4.7 s of EuRoC V1_01 (stereo-inertial), one agent through the "
        "same server as mission 'euroc-v101'.</p>", real_data_html(out, summary),
        "</body></html>\n"]
    with open(os.path.join(report, "index.html"), "w") as f:
        f.write("\n".join(parts))
