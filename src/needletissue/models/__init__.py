"""The models built on the FE engine (``needletissue.fem``), geometry, imaging and the Ritz theory.

One module or subpackage per model, each with its config, run function, results and figures:

* ``traction``: the soft-tissue traction validation (paper Sec. 3.2)
* ``needle``: the needle-tissue-bone model (``fe needle``), its figures and mesh-convergence study
* ``pelvis``: the anatomical model (``fe pelvis``) and its report
* ``contact``: the paper's frictional interfaces as an option of the needle and pelvis models
* ``contact_verify``: contact verification problems (stacked and pressed blocks) with known answers

See docs/architecture.md for what each layer may import.
"""
