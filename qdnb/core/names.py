"""The thesis's names for the book's environments, wherever a reader sees one: titles,
tables, legends, claims."""

ENV_LABELS = {
    "pointmaze": "Point-Maze",
    "antmaze": "Ant-Maze",
    "anttrap": "Ant-Trap",
    "ant_omni": "Ant-Omni",
    "halfcheetah_uni": "Halfcheetah-Uni",
}
