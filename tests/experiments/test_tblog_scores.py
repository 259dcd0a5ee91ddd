"""TensorBoard gets the baselines' scores beside the registration's: what the run must beat."""
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from indreg.experiments.tblog import RunWriter


def test_baselines_scores_are_scalars(tmp_path):
    writer = RunWriter(tmp_path, None, 0.0, 1.0)
    values = {"ssim": 0.8855, "fbp_ssim": 0.3938, "fbp_psnr": 17.21, "tv_ssim": 0.6185, "tv_psnr": 19.51,
              "template_ssim": 0.3741, "template_psnr": 8.44}
    writer.baselines(values, ["fbp", "tv", "sirt"], 200)
    writer.close()
    events = EventAccumulator(str(tmp_path))
    events.Reload()
    got = {tag: events.Scalars(tag)[-1] for tag in events.Tags()["scalars"]}
    assert sorted(got) == ["metrics/fbp_psnr", "metrics/fbp_ssim", "metrics/template_psnr", "metrics/template_ssim",
                           "metrics/tv_psnr", "metrics/tv_ssim"]          # no sirt: not in the run
    assert abs(got["metrics/tv_ssim"].value - 0.6185) < 1e-6 and got["metrics/tv_ssim"].step == 200
