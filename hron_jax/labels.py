"""The paper's names of the model variants, as its tables print them.

    LABELS[model]                          e.g. 'rgbd_sg_attn' -> 'RGB-D + SG + TD ATTN'
    paper_label(model, symbolic, premap)   the row name of one table cell

symbolic: the relational object choice task, whose scene-graph models see only the graph (the
paper's Table I drops 'RGB-D + ' there); premap: the 'PM: ' rows of pre-mapped navigation.
Imports nothing else, so tools/reproduce.py --plan can name its cells on a machine without JAX.
"""

LABELS = {
    'rgbd': 'RGB-D only',
    'rgbd_mm': 'RGB-D + MM',
    'rgbd_sg': 'RGB-D + SG',
    'rgbd_sg_attn': 'RGB-D + SG + TD ATTN',
    'gcn': 'Kipf et al. (GCN)',
    'yang': 'Yang et al.',
}


def paper_label(model: str, symbolic: bool = False, premap: bool = False) -> str:
    label = LABELS[model]
    if symbolic:
        label = label.replace('RGB-D + ', '')
    return 'PM: ' + label if premap else label
