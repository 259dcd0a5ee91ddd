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
    assert len(_colourbars(fig)) == 10   # template, 4 times, target, FBP, TV, two error maps
    bar = _colourbars(fig)[0]
    assert bar.get_ylim() == (float(trajectory[-1].min()), float(trajectory[-1].max()))   # the target's scale
    titles = [ax.get_title() for ax in _panels(fig)]
    assert "FBP\n(values -1 to 2)" in titles
    template = _panels(fig)[0]
    assert template.get_images()[0].get_extent() == [-16, 16, -8, 8] and template.get_xlabel() == "x"


def test_paper_figure_scores_every_method_and_maps_errors_and_residuals_signed():
    """Every method's SSIM / PSNR in its title, axes and scale bar in the unit, the error result - target and
    the residual sinogram T f - g on a diverging map symmetric about 0."""
    trajectory = _images(k=5)
    target = trajectory[-1] + 0.5
    residual = np.outer(np.arange(3) - 1.0, np.ones(8))      # 3 angles x 8 bins, -1..1
    score = {"result": {"ssim": 0.8855, "psnr": 24.19, "residual": 0.245}, "fbp": {"ssim": 0.39, "psnr": 17.2},
             "tv": {"ssim": 0.62, "psnr": 19.5}}
    fig = figures.paper_figure(trajectory[0], trajectory, target, np.linspace(-1, 1, 8), None, np.ones(8),
                               fbp=trajectory[1], tv=trajectory[2], extent=(-16, 16, -16, 16), scores=score,
                               residual=residual, angles_deg=[0.0, 60.0, 120.0], unit="nm")
    panels = _panels(fig)
    titles = [ax.get_title() for ax in panels]
    assert "$t=1.00$ (result)\nSSIM 0.8855, PSNR 24.19 dB" in titles
    assert any(t.startswith("FBP\nSSIM 0.3900, PSNR 17.20 dB") for t in titles)
    assert any(t.startswith("TV\nSSIM 0.6200, PSNR 19.50 dB") for t in titles)
    assert panels[0].get_xlabel() == "x (nm)"
    bars = [a for a in panels[0].artists if hasattr(a, "txt_label")]
    assert [b.txt_label.get_text() for b in bars] == ["5 nm"]
    error, best, sino = panels[-3:]
    assert error.get_title() == "error: result $-$ target"
    image = error.get_images()[0]
    np.testing.assert_allclose(np.rot90(trajectory[-1] - target), image.get_array())
    bound = max(np.abs(trajectory[k] - target).max() for k in (2, 4))   # the best baseline (TV), the result
    assert image.get_cmap().name == figures.DIVERGING and image.get_clim() == (-bound, bound)
    assert best.get_title() == "error: TV $-$ target (same scale)"   # the best baseline by SSIM
    assert best.get_images()[0].get_clim() == (-bound, bound)
    assert sino.get_images()[0].get_clim() == (-1.0, 1.0) and "data residual 0.2450" in sino.get_title()
    assert [t.get_text() for t in sino.get_yticklabels()] == ["0", "60", "120"]
    assert sino.get_xlabel() == "detector coordinate (nm)"


def test_sirt_joins_the_best_baseline_and_the_data_panel_names_its_axis():
    """SIRT (given) is a candidate of the error row's best baseline; the data panel's y axis says what it plots;
    the app names the length unit "a.u." when ``logging.length_unit`` is unset (the paper's box has none)."""
    from indreg.experiments import run_figures

    trajectory = _images(k=5)
    score = {"result": {"ssim": 0.9, "psnr": 24.0}, "fbp": {"ssim": 0.3, "psnr": 17.0},
             "sirt": {"ssim": 0.8, "psnr": 22.0}, "tv": {"ssim": 0.6, "psnr": 19.0}}
    fig = figures.paper_figure(trajectory[0], trajectory, trajectory[-1] + 0.5, np.linspace(-1, 1, 8), None,
                               np.ones(8), fbp=trajectory[1], tv=trajectory[2], sirt=trajectory[3],
                               extent=(-16, 16, -16, 16), scores=score, unit="a.u.")
    panels = _panels(fig)
    assert panels[-2].get_title() == "error: SIRT $-$ target (same scale)"
    data = next(ax for ax in panels if ax.get_title().startswith("Data at"))
    assert data.get_ylabel() == "line integral" and data.get_xlabel() == "detector coordinate (a.u.)"
    assert [b.txt_label.get_text() for b in panels[0].artists if hasattr(b, "txt_label")] == ["5 a.u."]
    assert run_figures._unit(type("C", (), {"logging": type("L", (), {"length_unit": None})})()) == "a.u."


def test_score_text_falls_back_to_the_residuals_without_truth():
    assert figures.score_text({"ssim": 0.5, "psnr": 20.0}) == "SSIM 0.5000, PSNR 20.00 dB"
    assert figures.score_text({"residual": 0.1, "holdout_residual": 0.2}) == "held-out residual 0.2000"
    assert figures.score_text({"residual": 0.1}) == "data residual 0.1000"
    assert figures.score_text(None) == ""


def test_scale_bar_is_a_round_length_of_at_most_a_quarter_of_the_width():
    assert figures.scale_bar_length(32.0) == 5.0
    assert figures.scale_bar_length(860.16) == 200.0
    assert figures.scale_bar_length(4.0) == 1.0
    assert figures.scale_bar_length(0.3) == 0.05


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


def test_movie_has_a_real_frame_delay_and_a_time_label(tmp_path):
    """0.25 s per frame (imageio's GIF writer takes milliseconds: 0.25 would be 0), each frame labelled."""
    from PIL import Image

    frames = np.zeros((2, 24, 24))
    figures.save_gif(frames, tmp_path / "m.gif", 0.0, 1.0, labels=["t = 0.5", "t = 1"])
    with Image.open(tmp_path / "m.gif") as gif:
        assert gif.n_frames == 2 and gif.info["duration"] == 250
    plain = figures.gif_frames(frames, 0.0, 1.0)[0]
    labelled = figures.gif_frames(frames, 0.0, 1.0, ["t = 0.5", "t = 1"])[0]
    assert plain.max() == 0 and labelled.shape == (264, 264, 3) and labelled.max() > 0   # the label's pixels


def test_parts_figure_draws_the_intensity_part_diverging_and_names_the_model():
    final = _images(n=16, k=1)[0]
    fig = figures.parts_figure(final, final, final - 0.5, target=final, title="SSIM 0.9")
    assert fig._suptitle.get_text() == "metamorphosis: SSIM 0.9"
    part = _panels(fig)[2].get_images()[0]
    assert part.get_cmap().name == figures.DIVERGING and part.get_clim() == (-0.5, 0.5)
