"""The renderer's arithmetic against references: float32 and bfloat16 against float64, the
specular models against quadrature, our shading against Mitsuba, what the SG model cannot
represent, and Mitsuba's own variants."""
