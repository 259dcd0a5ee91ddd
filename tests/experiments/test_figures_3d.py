"""Orthogonal slices of volumes: which planes, the figure's layout, TensorBoard's montage."""
import numpy as np
import pytest

from indreg.experiments import figures
from indreg.experiments.tblog import to_display


def volume(nx=6, ny=8, nz=10):
    x, y, z = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    return 100.0 * x + 10.0 * y + z  # each voxel's value names its indices


def test_orthoslices_are_the_central_planes():
    xy, xz, yz = figures.orthoslices(volume())
    assert xy.shape == (6, 8) and xz.shape == (6, 10) and yz.shape == (8, 10)
    assert np.all(xy % 10 == 5)                 # z = nz // 2 = 5
    assert np.all((xz // 10) % 10 == 4)         # y = ny // 2 = 4
    assert np.all(yz // 100 == 3)               # x = nx // 2 = 3
    with pytest.raises(ValueError, match=r"volume \(nx, ny, nz\)"):
        figures.orthoslices(np.zeros((4, 4)))


def panels(fig) -> list:
    """The figure's axes but its colour bars."""
    return [ax for ax in fig.get_axes() if ax.get_label() != "<colorbar>"]


def test_ortho_figure_rows_and_columns():
    fig = figures.ortho_figure([("template", volume()), ("FBP", None), ("target", volume())], title="t")
    axes = panels(fig)
    assert len(axes) == 9 and len(fig.get_axes()) == 9 + 2    # a colour bar per shown row
    assert [ax.get_title() for ax in axes[:3]] == ["template: xy", "xz", "yz"]   # the row's label on its first plane
    assert axes[3].get_title() == "FBP (off)" and not axes[4].axison


def test_to_display_of_a_volume_is_three_upright_slices():
    v = volume()
    tile = to_display(v, float(v.min()), float(v.max()))
    # heights: max of the rotated slices (ny=8, nz=10, nz=10); widths 6 + 2 + 6 + 2 + 8
    assert tile.shape == (1, 10, 24)
    assert tile.min() >= 0.0 and tile.max() <= 1.0
    xy = to_display(figures.orthoslices(v)[0], float(v.min()), float(v.max()))
    assert np.array_equal(tile[:, 2:, :6], xy)  # bottom-aligned, padded white above
    assert np.all(tile[:, :2, :6] == 1.0)


def test_parts_ortho_figure_rows_and_the_intensity_rows_own_scale():
    v = volume()
    change = np.zeros_like(v)
    change[1, 2, 3] = -0.5
    fig = figures.parts_ortho_figure(v + change, v, change, target=v)
    axes = panels(fig)
    assert len(axes) == 12
    assert [ax.get_title() for ax in axes[::3]] == ["f(1): xy", "W(nu, I): xy", "f(1) - W(nu, I) (+-0.5): xy",
                                                  "target: xy"]
    assert axes[6].get_images()[0].get_cmap().name == figures.DIVERGING
    assert fig._suptitle.get_text() == "metamorphosis"
    assert axes[3].get_images()[0].get_clim() == (float(v.min()), float(v.max()))
    assert axes[6].get_images()[0].get_clim() == (-0.5, 0.5)


def test_ortho_figure_axes_in_the_domains_units():
    """With the domain's box the slices are drawn on its coordinates: xy spans x and y, xz x and z, yz y and z."""
    fig = figures.ortho_figure([("template", volume())], box=((-3, -4, -5), (3, 4, 5)))
    xy, xz, yz = panels(fig)
    assert xy.get_images()[0].get_extent() == [-3, 3, -4, 4] and (xy.get_xlabel(), xy.get_ylabel()) == ("x", "y")
    # the planes' positions: cells 5 of 10 (z), 4 of 8 (y), 3 of 6 (x), centres at 0.5
    assert [ax.get_title() for ax in (xy, xz, yz)] == ["template: xy at z = 0.5", "xz at y = 0.5", "yz at x = 0.5"]
    two_lines = figures.ortho_figure([("FBP\nSSIM 0.3", volume())])
    assert panels(two_lines)[0].get_title() == "FBP\nSSIM 0.3\nxy"   # a label of several lines: the plane below
    assert xz.get_images()[0].get_extent() == [-3, 3, -5, 5] and (xz.get_xlabel(), xz.get_ylabel()) == ("x", "z")
    assert yz.get_images()[0].get_extent() == [-4, 4, -5, 5] and (yz.get_xlabel(), yz.get_ylabel()) == ("y", "z")


def test_ortho_figure_in_nm_marks_the_tilt_axis_and_the_missing_wedge():
    """A tilt series about y: the axis dashed in xy (x = 0) and yz (z = 0), the first and last tilts' beam
    directions dotted in xz; a row on its own scale keeps it."""
    v = volume()
    fig = figures.ortho_figure([("template", v), ("SIRT", v * 10, (0.0, 5000.0))], box=((-3, -4, -5), (3, 4, 5)),
                               unit="nm", tilt={"axis": "y", "range_deg": (-60.0, 60.0)})
    xy, xz, yz, sirt = panels(fig)[:4]
    assert xy.get_xlabel() == "x (nm)" and xy.get_title() == "template: xy at z = 0.5 nm"
    assert [tuple(line.get_xdata()) for line in xy.get_lines()] == [(0.0, 0.0)]
    assert [tuple(line.get_ydata()) for line in yz.get_lines()] == [(0.0, 0.0)]
    beams = [np.degrees(np.arctan2(-np.diff(line.get_xdata())[0], np.diff(line.get_ydata())[0]))
             for line in xz.get_lines()]
    np.testing.assert_allclose(beams, [-60.0, 60.0])
    assert "missing wedge" in " ".join(t.get_text() for t in xz.texts)
    assert sirt.get_images()[0].get_clim() == (0.0, 5000.0)
