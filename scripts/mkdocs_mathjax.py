"""MkDocs hook: MathJax served with the site, not fetched from a CDN.

The site's formulas (pymdownx.arithmatex, generic mode) are typeset in the browser by MathJax 3's
SVG build (``es5/tex-svg.js``: fonts inside, one file), which ``npm ci`` installs from
package.json into ``node_modules/mathjax``; this hook adds that file to the site as
``javascripts/vendor/mathjax/tex-svg.js`` (mkdocs.yml's extra_javascript), with MathJax's licence
beside it, so that the site works offline. Without it the build stops, saying how to get it.
"""

from __future__ import annotations

from pathlib import Path

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File

#: MathJax's package, as npm ci installs it (package.json pins the version)
PACKAGE = Path(__file__).resolve().parents[1] / "node_modules" / "mathjax"
#: where the site serves it (mkdocs.yml's extra_javascript names the script)
SITE_PATH = "javascripts/vendor/mathjax"


def on_files(files, config):
    script = PACKAGE / "es5" / "tex-svg.js"
    if not script.is_file():
        raise PluginError(
            f"MathJax is missing ({script}): the site serves it itself. Run npm ci in the repository root "
            "(bash scripts/setup.sh does), then build again."
        )
    for name, source in (("tex-svg.js", script), ("LICENSE", PACKAGE / "LICENSE")):
        files.append(File.generated(config, f"{SITE_PATH}/{name}", abs_src_path=str(source)))
    return files
