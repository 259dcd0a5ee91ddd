"""The 2D figures a scientist reads: colour bars, axes in the domain's units, frames labelled by their times, a
movie large enough to watch."""
import imageio.v2 as imageio
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg

from indreg.experiments import figures


def _colourbars(fig) -> list:
    return [ax for ax in fig.get_axes() if ax.get_label() == "<colorbar>"]


def _panels(fig) -> list:
    return [ax for ax in fig.get_axes() if ax.get_label() != "<colorbar>"]


def _images(n=8, k=5):
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    return np.stack([x + t * y for t in range(k)])


def test_paper_figure_has_a_colour_bar_per_image_and_states_the_baselines_range():
    trajectory = _images(k=5)          # N = 4
    fbp = trajectory[0] * 3 - 1        # beyond the target's grey scale
    fig = figures.paper_figure(trajectory[0], trajectory, trajectory[-1], np.arange(8), None, np.ones(8), fbp=fbp,
                               tv=trajectory[-1], extent=(-16, 16, -8, 8), title="t")
    assert len(_colourbars(fig)) == 8   # template, 4 times, target, FBP, TV
    bar = _colourbars(fig)[0]
    assert bar.get_ylim() == (float(trajectory[-1].min()), float(trajectory[-1].max()))   # the target's scale
    titles = [ax.get_title() for ax in _panels(fig)]
    assert "FBP (values -1 to 2)" in titles
    template = _panels(fig)[0]
    assert template.get_images()[0].get_extent() == [-16, 16, -8, 8] and template.get_xlabel() == "x"


def test_parts_figure_titles_keep_clear_of_the_suptitle():
    """The panel titles stay at least 5 px below the figure's title (the former 1 x 4 layout: 1.3 px, touching)."""
    final = _images(n=32, k=1)[0]
    fig = figures.parts_figure(final, final, final * 0.1 - 0.05, target=final, extent=(-16, 16, -16, 16),
                               title="suite1_jv: SSIM 0.6414, PSNR 14.01 dB")
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    top = fig._suptitle.get_window_extent(renderer)
    for ax in _panels(fig):
        assert top.y0 - ax.title.get_window_extent(renderer).y1 >= 5, ax.get_title()
    assert len(_colourbars(fig)) == 4


def test_frames_figure_labels_frames_by_their_times():
    frames = _images(k=3)
    fig = figures.frames_figure(frames, frames, times=[0.25, 0.5, 1.0])
    assert [ax.get_title() for ax in _panels(fig)[:3]] == ["$t=0.25$", "$t=0.5$", "$t=1$"]
    assert len(_colourbars(fig)) == 1
    fig = figures.frames_figure(frames)
    assert [ax.get_title() for ax in _panels(fig)] == ["k=1", "k=2", "k=3"]


def test_movie_is_upscaled_nearest_to_256_pixels(tmp_path):
    frames = _images(n=24, k=2)
    figures.save_gif(frames, tmp_path / "m.gif", 0.0, 2.0)
    first = np.asarray(imageio.mimread(tmp_path / "m.gif")[0])
    assert first.shape[:2] == (264, 264)                     # 24 x 11: the least factor reaching 256
    assert np.array_equal(figures.upscale(np.arange(6).reshape(2, 3), side=7), np.repeat(np.repeat(
        np.arange(6).reshape(2, 3), 3, axis=0), 3, axis=1))
    assert figures.upscale(np.zeros((300, 20))).shape == (300, 20)
