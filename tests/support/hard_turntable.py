"""The twin of a hard real turntable, as synthetic capture options: a glossy plain
specimen on a dotted plate, no board, no EXIF focal length, one ring of views."""


def hard_turntable_options(**overrides) -> dict:
    """``SynthOptions`` keywords of the hard turntable twin, ``overrides`` on top."""
    return {
        "calibration_shots": 0,
        "rig": "turntable",
        "rings": (25.0,),
        "material": "glossy_paint",
        "texture": "plain",
        "table": "dots",
        "exif_focal": False,
    } | overrides
