"""Recovery on Mitsuba's ground truth across meshes and presets, the recovery tests' cases, the
relighting error budget and levers, and the robustness study's table."""
