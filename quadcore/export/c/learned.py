"""The learned part in C: XGBoost trees as node arrays, or the MLP's weights with its scaling.

Both write ``static void qc_learned(const float x[QC_N_FEATURES], float y[6])``: raw
features in, residual force (N) and torque (N m) out, body frame.

**Trees.** The Python model standardises the inputs, ``z = float32((x - mean) / std)``
computed in double, and sends ``z < threshold`` left. That comparison is moved onto the raw
input: for every split the exporter finds the smallest float32 ``x*`` with
``float32((x* - mean) / std) >= threshold`` (by bisection over the float32 values), so
``x < x*`` takes exactly the branch Python takes, for every float32 ``x``, and the C code
does no scaling at all. A NaN input goes the tree's default way, as in XGBoost. Leaves are
summed per output in float, then ``y * std + mean``.

**MLP.** ``z = (x - mean) / std`` with the reciprocal stored, the layers (ReLU between them)
in float, then ``y * std + mean``.
"""

from __future__ import annotations

import numpy as np

from quadcore.effects.c_inputs import ExportError
from quadcore.learn.artefacts import LearnedModel
from quadcore.learn.backends import backend
from quadcore.learn.trees import CompiledForest


def c_float(value: float) -> str:
    """A float literal that round-trips float32 (``INFINITY`` for +-inf)."""
    v = np.float32(value)
    if np.isnan(v):
        raise ExportError("a model constant is NaN")
    if np.isinf(v):
        return "INFINITY" if v > 0 else "-INFINITY"
    text = np.format_float_scientific(v, unique=True, trim="0") if v != 0 else "0.0"
    return text.replace("e+", "e") + "f"


def float_table(name: str, values, per_line: int = 6) -> str:
    """``static const float name[n]`` (or ``[rows][cols]`` for a matrix) with float32 literals."""
    values = np.asarray(values, np.float64)

    def row(v) -> str:
        vals = [c_float(x) for x in v]
        return ",\n    ".join(", ".join(vals[i:i + per_line]) for i in range(0, len(vals), per_line))

    if values.ndim == 2:
        rows = ",\n    ".join("{" + row(v) + "}" for v in values)
        return f"static const float {name}[{values.shape[0]}][{values.shape[1]}] = {{\n    {rows}\n}};"
    return f"static const float {name}[{values.size}] = {{\n    {row(values.ravel())}\n}};"


def _ordered_key(x32: np.ndarray) -> np.ndarray:
    """float32 -> int64 keys in the same order (-0 and +0 share one)."""
    bits = x32.astype(np.float32).view(np.int32).astype(np.int64)
    return np.where(bits >= 0, bits, -(bits & 0x7FFFFFFF))


def _from_key(key: np.ndarray) -> np.ndarray:
    bits = np.where(key >= 0, key, (-key) | 0x80000000).astype(np.uint32)
    return bits.view(np.float32)


def raw_thresholds(threshold: np.ndarray, feature: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """Per split: the smallest float32 ``x*`` with ``float32((x* - mean) / std) >= threshold``,
    so that ``z < threshold`` iff ``x < x*`` (the scaling is monotonic: std > 0). Found by
    bisection over the ordered float32 values, between -inf and +inf."""
    t = np.asarray(threshold, np.float32)
    mu, sd = mean[feature], std[feature]
    lo = np.full(t.shape, _ordered_key(np.array([-np.inf], np.float32))[0])  # z(-inf) < t
    hi = np.full(t.shape, _ordered_key(np.array([np.inf], np.float32))[0])  # z(+inf) >= t
    with np.errstate(over="ignore", invalid="ignore"):
        while (hi - lo > 1).any():
            mid = (lo + hi) // 2
            at_or_above = ((_from_key(mid).astype(np.float64) - mu) / sd).astype(np.float32) >= t
            hi, lo = np.where(at_or_above, mid, hi), np.where(at_or_above, lo, mid)
    return _from_key(hi)


def _node_order(left: np.ndarray, right: np.ndarray, root: int) -> list[int]:
    """A tree's nodes breadth first, so that each split's two children are adjacent."""
    order, frontier = [root], [root]
    while frontier:
        nxt = [c for n in frontier if left[n] != n for c in (left[n], right[n])]
        order += nxt
        frontier = nxt
    return order


MAX_TREE_FEATURES = 32  # five bits of a node's first byte
LEFT_LEAF, RIGHT_LEAF, DEFAULT_LEFT = 0x20, 0x40, 0x80


def _cut_tables(forest: CompiledForest, model: LearnedModel) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Which nodes are leaves, every node's threshold on the raw input, and each feature's sorted
    split values (its cut table)."""
    n_features = len(model.features)
    if n_features > MAX_TREE_FEATURES:
        raise ExportError(f"the tree model has {n_features} features; the C node format holds {MAX_TREE_FEATURES}")
    is_leaf = forest.left == np.arange(len(forest.left))
    raw = forest.threshold.copy()
    raw[~is_leaf] = raw_thresholds(forest.threshold[~is_leaf], forest.feature[~is_leaf], model.x_scaler.mean,
                                   model.x_scaler.std)
    cuts = [np.unique(raw[~is_leaf & (forest.feature == f)]) for f in range(n_features)]
    worst = max(range(n_features), key=lambda f: len(cuts[f]))
    if len(cuts[worst]) > 256:
        raise ExportError(f"feature {model.features[worst]!r} has {len(cuts[worst])} distinct split values; the C node "
                          "format holds 256 (XGBoost's hist method with max_bin <= 256 stays within it)")
    return is_leaf, raw, cuts


def _tree_nodes(forest: CompiledForest, is_leaf: np.ndarray, raw: np.ndarray,
                cuts: list[np.ndarray]) -> tuple[list[str], list[int], list[int], np.ndarray]:
    """The C initialisers of every node, trees grouped by output; the index of each tree's first
    node; the number of trees per output; the base score per output with the single-leaf trees
    folded into it."""
    base = forest.base.astype(np.float64).copy()
    nodes: list[str] = []
    tree_start: list[int] = []
    trees_of = [0] * len(base)
    for t in np.argsort(forest.group, kind="stable"):
        root, g = int(forest.roots[t]), int(forest.group[t])
        if is_leaf[root]:  # a constant: part of the base score
            base[g] += forest.value[root]
            continue
        order = _node_order(forest.left, forest.right, root)
        if len(order) > 65535:
            raise ExportError(f"a tree has {len(order)} nodes; the C node format holds 65535")
        local = {n: k for k, n in enumerate(order)}
        tree_start.append(len(nodes))
        trees_of[g] += 1
        for n in order:
            if is_leaf[n]:
                nodes.append(f"{{.leaf = {c_float(forest.value[n])}}}")
                continue
            f, left, right = int(forest.feature[n]), forest.left[n], forest.right[n]
            flags = (f | (LEFT_LEAF if is_leaf[left] else 0) | (RIGHT_LEAF if is_leaf[right] else 0)
                     | (DEFAULT_LEFT if forest.default_left[n] else 0))
            b = int(np.searchsorted(cuts[f], raw[n]))
            nodes.append(f"{{.split = {{{flags}, {b}, {local[left]}}}}}")
    return nodes, tree_start, trees_of, base


# The evaluation of the node arrays: rank each input in its cut table, then walk every tree.
QC_LEARNED_C = f"""static void qc_learned(const float x[QC_N_FEATURES], float y[6])
{{
    short rank[QC_N_FEATURES];  /* how many cuts of feature f are <= x_f; -1 for NaN */
    int f, k;
    unsigned t;
    for (f = 0; f < QC_N_FEATURES; ++f) {{
        unsigned lo = QC_CUT_START[f], hi = QC_CUT_START[f + 1];
        const unsigned first_cut = lo;
        if (isnan(x[f])) {{
            rank[f] = -1;
            continue;
        }}
        while (lo < hi) {{
            const unsigned mid = (lo + hi) / 2;
            if (QC_CUTS[mid] <= x[f]) lo = mid + 1; else hi = mid;
        }}
        rank[f] = (short)(lo - first_cut);
    }}
    for (k = 0; k < 6; ++k) {{
        float sum = 0.0f;
        for (t = QC_FIRST_TREE[k]; t < QC_FIRST_TREE[k + 1]; ++t) {{
            const qc_node *tree = QC_NODES + QC_TREE_START[t];
            unsigned n = 0;
            for (;;) {{
                const unsigned flags = tree[n].split.feature_flags;
                const short r = rank[flags & 31u];
                const int go_left = r >= 0 ? r <= (short)tree[n].split.bin : (flags & {DEFAULT_LEFT}u) != 0;
                const unsigned child = tree[n].split.left + (go_left ? 0u : 1u);
                if (flags & (go_left ? {LEFT_LEAF}u : {RIGHT_LEAF}u)) {{
                    sum += tree[child].leaf;
                    break;
                }}
                n = child;
            }}
        }}
        y[k] = (sum + QC_BASE[k]) * QC_Y_STD[k] + QC_Y_MEAN[k];
    }}
}}
"""


def trees_c(model: LearnedModel) -> tuple[str, dict]:
    """C for an XGBoost model and figures about it.

    Each feature's split values (raw scale, see :func:`raw_thresholds`) are sorted into a cut
    table (XGBoost's ``hist`` uses at most 256 per feature). Per call the C code ranks every
    input once (how many of its cuts are <= x, by bisection); ``x < cut[b]`` is then
    ``rank <= b``. A node is 4 bytes: a split (feature and flags, cut index, index of its left
    child; the right child follows it) or a leaf value. Single-leaf trees fold into the base.
    """
    forest = CompiledForest(model.impl)
    is_leaf, raw, cuts = _cut_tables(forest, model)
    nodes, tree_start, trees_of, base = _tree_nodes(forest, is_leaf, raw, cuts)
    first = np.concatenate([[0], np.cumsum(trees_of)])
    cut_start = np.concatenate([[0], np.cumsum([len(c) for c in cuts])])
    all_cuts = np.concatenate(cuts) if cut_start[-1] else np.zeros(1)
    start_type = "unsigned short" if len(nodes) <= 65535 else "unsigned long"
    nodes_text = ",\n    ".join(nodes) if nodes else "{.leaf = 0.0f}"
    code = f"""/* XGBoost: {len(tree_start)} trees, {len(nodes)} nodes (single-leaf trees folded into the base).
   A split sends input f left when x_f < cut (rank(x_f) <= bin), else right; its right child follows its left;
   a NaN input goes left when the default-left flag is set. Flags: bits 0-4 feature, 0x20 left child is a
   leaf, 0x40 right child is a leaf, 0x80 default left. Cuts are on the raw inputs: exactly the branches of
   the standardised Python model. */
typedef union {{
    struct {{ unsigned char feature_flags, bin; unsigned short left; }} split;
    float leaf;
}} qc_node;
static const qc_node QC_NODES[{max(len(nodes), 1)}] = {{
    {nodes_text}
}};
static const {start_type} QC_TREE_START[{max(len(tree_start), 1)}] = {{{", ".join(map(str, tree_start)) or "0"}}};
/* output k: trees [first[k], first[k+1]) */
static const unsigned short QC_FIRST_TREE[7] = {{{", ".join(str(int(v)) for v in first)}}};
{float_table("QC_CUTS", all_cuts)}
static const unsigned short QC_CUT_START[QC_N_FEATURES + 1] = {{{", ".join(str(int(v)) for v in cut_start)}}};
{float_table("QC_BASE", base)}  /* XGBoost base score per output */
{float_table("QC_Y_MEAN", model.y_scaler.mean)}
{float_table("QC_Y_STD", model.y_scaler.std)}

""" + QC_LEARNED_C
    figures = {"kind": "xgboost", "trees": len(tree_start), "nodes": len(nodes), "trees_per_output": trees_of,
               "max_depth": int(forest.depth), "cuts": int(cut_start[-1])}
    return code, figures


def mlp_c(model: LearnedModel) -> tuple[str, dict]:
    """C for an MLP (weights, biases, the scalers) and figures about it."""
    layers = backend("mlp").linear_layers(model.impl)
    tables, widths = [], [layers[0].in_features]
    for k, layer in enumerate(layers):
        w = layer.weight.detach().numpy().astype(np.float64)
        b = layer.bias.detach().numpy().astype(np.float64)
        tables.append(float_table(f"QC_W{k}", w, per_line=8))
        tables.append(float_table(f"QC_B{k}", b))
        widths.append(w.shape[0])
    width = max(widths)
    steps = []
    for k, layer in enumerate(layers):
        relu = k < len(layers) - 1
        src, dst = ("a", "b") if k % 2 == 0 else ("b", "a")
        act = f"{dst}[o] = acc > 0.0f ? acc : 0.0f;" if relu else f"{dst}[o] = acc;"
        what = f"layer {k}: {layer.in_features} -> {layer.out_features}{', ReLU' if relu else ''}"
        steps.append(f"""    for (o = 0; o < {layer.out_features}; ++o) {{  /* {what} */
        float acc = QC_B{k}[o];
        for (i = 0; i < {layer.in_features}; ++i) acc += QC_W{k}[o][i] * {src}[i];
        {act}
    }}""")
    out = "b" if len(layers) % 2 == 1 else "a"
    xs, ys = model.x_scaler, model.y_scaler
    newline = "\n"
    code = f"""/* MLP {' -> '.join(map(str, widths))} (ReLU between layers), float weights; inputs and outputs
   standardised with the training flights' statistics. */
{newline.join(tables)}
{float_table("QC_X_MEAN", xs.mean)}
{float_table("QC_X_INV_STD", 1.0 / xs.std)}
{float_table("QC_Y_MEAN", ys.mean)}
{float_table("QC_Y_STD", ys.std)}

static void qc_learned(const float x[QC_N_FEATURES], float y[6])
{{
    float a[{width}], b[{width}];
    int i, o;
    for (i = 0; i < QC_N_FEATURES; ++i) a[i] = (x[i] - QC_X_MEAN[i]) * QC_X_INV_STD[i];
{newline.join(steps)}
    for (o = 0; o < 6; ++o) y[o] = {out}[o] * QC_Y_STD[o] + QC_Y_MEAN[o];
}}
"""
    macs = sum(layer.in_features * layer.out_features for layer in layers)
    return code, {"kind": "mlp", "widths": widths, "multiply_adds": macs}


def learned_c(model: LearnedModel) -> tuple[str, dict]:
    if model.kind == "xgboost":
        return trees_c(model)
    if model.kind == "mlp":
        return mlp_c(model)
    raise ExportError(f"no C form for learned model kind {model.kind!r}")
