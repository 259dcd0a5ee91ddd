"""alignment.png states only what was estimated: the tilt-axis angle only when the mode estimated it."""
import matplotlib.image

from indreg.alignment import plot_shifts


def _alignment(mode: str) -> dict:
    return {"mode": mode, "components": ["across", "along"], "tilt_angles_deg": [-30.0, 0.0, 30.0],
            "shifts_px": [[0.1, 0.0], [0.0, 0.2], [-0.1, 0.0]], "axis_angle_deg": 0.0}


def test_the_title_names_the_axis_angle_only_when_it_was_estimated(tmp_path, monkeypatch):
    titles = []
    import matplotlib.axes

    original = matplotlib.axes.Axes.set_title
    monkeypatch.setattr(matplotlib.axes.Axes, "set_title",
                        lambda self, text, *a, **k: titles.append(text) or original(self, text, *a, **k))
    plot_shifts(_alignment("shifts"), tmp_path / "a.png")
    plot_shifts(_alignment("shifts+axis") | {"axis_angle_deg": -3.69}, tmp_path / "b.png")
    assert titles == ["alignment (shifts) (tilt-axis angle not estimated)",
                      "alignment (shifts+axis): tilt-axis angle -3.690 deg"]
    assert matplotlib.image.imread(tmp_path / "a.png").shape[2] in (3, 4)
