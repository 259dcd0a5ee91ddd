"""data=files runs register()'s defaults for a user's own data (the kernel width relative to the box, compose);
the paper's presets and the recorded own-data example keep theirs."""
from experiment_helpers import compose


def test_files_take_the_defaults_and_the_presets_keep_theirs():
    files = compose(["data=files"])
    assert files.kernel.sigma is None and files.deformation.interpolation == "compose"
    paper = compose([])                                              # suite 1
    assert paper.kernel.sigma == 6.0 and paper.deformation.interpolation is None   # the model's rule: reinterpolate
    example = compose(["experiment=own_data_example"])
    assert example.kernel.sigma == 3.0 and example.deformation.interpolation is None
    assert compose(["data=files", "kernel.sigma=auto"]).kernel.sigma == "auto"
