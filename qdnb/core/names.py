"""The thesis's names for the book's environments, wherever a reader sees one: titles,
tables, legends, claims."""

ENV_LABELS = {
    "pointmaze": "Point-Maze",
    "antmaze": "Ant-Maze",
    "anttrap": "Ant-Trap",
    "ant_omni": "Ant-Omni",
    "halfcheetah_uni": "Halfcheetah-Uni",
}

# What a reader sees for the book's other internal names (a predictor, a sweep's variant)
# when a table shows one.
READER_NAMES = {
    **ENV_LABELS,
    "flt": "FLT",
    "flt_teacher_forced": "FLT, true inputs (one step)",
    "mean_frame": "mean frame",
}
