"""The README's Python quick start runs as written, and its comments say what it returns."""
import pathlib
import re

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_readme_quick_start_runs_and_its_shapes_are_as_commented():
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(blocks) == 1, "the README has one Python quick start"
    namespace = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)      # noqa: S102 - the README's own code
    bench, model, mode = namespace["bench"], namespace["model"], namespace["mode"]
    frames = len(bench.observations)
    # "(frames, 3 * nodes): sd of the nodal strains, row 3 i + c, c = e_xx, e_yy, gamma_xy"
    strain_sd = mode.output_sd["strain"]
    assert strain_sd.shape == (frames, 3 * bench.mesh.n_nodes)
    assert np.all(np.isfinite(strain_sd)) and np.all(strain_sd >= 0)
    assert "(frames, 3 * nodes)" in blocks[0]
    material = namespace["material"]                                  # "per-element E (Pa) and nu"
    E, nu = material.E, material.nu
    assert E.shape == nu.shape == (bench.mesh.n_elements,)
    assert np.all(E > 0) and np.all((nu > 0) & (nu < 0.5))
