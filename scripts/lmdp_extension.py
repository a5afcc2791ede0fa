"""Load LMDP Light Transport into a running Blender (or PyPI bpy) the way Blender does.

Used by ``scripts/lmdp_headless.py`` and by the add-on tests (``tests/addon/conftest.py``):

* :func:`find_enabled` / :func:`find_installed`: an extension ``bl_ext.<repo>.lmdp_light_transport``
  already installed in the user's Blender.
* :func:`register_checkout`: make a source checkout an extension without building a zip: a
  directory holding a symlink ``lmdp_light_transport -> <checkout>`` is registered as a user
  extension repository (``preferences.extensions.repos.new(..., source='USER')``) and the add-on
  is enabled with ``addon_utils.enable``. The module name is the symlink's name, so it does not
  depend on what the checkout folder is called.

Blender and wheels: enabling an extension makes Blender install the wheels listed in its
manifest (for this platform) into ``<user resources>/extensions/.local/lib/python3.11/
site-packages``. Entries whose file does not exist are skipped without a message, so a checkout
without ``wheels/`` (before ``make extension``) imports scipy and embreex from the Python
environment instead (the venv, with PyPI bpy); after ``make extension`` Blender extracts the
linux wheels from ``wheels/``, exactly as for an installed zip.
"""
import os

EXTENSION_ID = "lmdp_light_transport"
EXTENSION_PREFIX = "bl_ext."


def is_lmdp_module(module_name):
    return module_name.startswith(EXTENSION_PREFIX) and module_name.endswith("." + EXTENSION_ID)


def find_enabled():
    """Module name of an enabled ``bl_ext.*.lmdp_light_transport``, or None."""
    import bpy
    for addon in bpy.context.preferences.addons:
        if is_lmdp_module(addon.module):
            return addon.module
    return None


def find_installed():
    """Module name of an installed (maybe disabled) ``bl_ext.*.lmdp_light_transport``, or None."""
    import addon_utils
    for module in addon_utils.modules(refresh=True):
        if is_lmdp_module(module.__name__):
            return module.__name__
    return None


def _raise(error):
    raise error


def enable(module_name):
    """Enable the add-on ``module_name``; raises the add-on's own error if it fails."""
    import addon_utils
    import bpy
    addon_utils.enable(module_name, default_set=True, persistent=True, handle_error=_raise)
    if module_name not in bpy.context.preferences.addons:
        raise RuntimeError(f"Blender did not enable {module_name} (see the console output above)")
    return module_name


def register_checkout(checkout, repo_directory, repo_module="lmdp_checkout", repo_name="LMDP checkout"):
    """Register ``checkout`` as an extension through a temporary repository and enable it.

    ``repo_directory`` is created if needed and receives the ``lmdp_light_transport`` symlink.
    Returns ``(module_name, repo)``; undo with :func:`unregister_checkout`.
    """
    import bpy
    checkout = os.path.realpath(checkout)
    if not os.path.isfile(os.path.join(checkout, "blender_manifest.toml")):
        raise FileNotFoundError(f"{checkout} is not an extension checkout (no blender_manifest.toml)")
    repo_directory = os.path.abspath(repo_directory)
    os.makedirs(repo_directory, exist_ok=True)
    link = os.path.join(repo_directory, EXTENSION_ID)
    if os.path.islink(link) and os.path.realpath(link) != checkout:
        os.remove(link)
    if not os.path.lexists(link):
        os.symlink(checkout, link, target_is_directory=True)
    repos = bpy.context.preferences.extensions.repos
    repo = next((r for r in repos if r.module == repo_module), None)
    if repo is None:
        repo = repos.new(name=repo_name, module=repo_module, custom_directory=repo_directory, source='USER')
    module_name = f"{EXTENSION_PREFIX}{repo.module}.{EXTENSION_ID}"
    return enable(module_name), repo


def unregister_checkout(module_name, repo):
    """Remove the temporary repository of :func:`register_checkout` and disable the add-on.

    Removing a repository makes Blender disable the add-ons it holds; whatever is still enabled
    afterwards is disabled explicitly.
    """
    import addon_utils
    import bpy
    repos = bpy.context.preferences.extensions.repos
    if repo is not None and any(r == repo for r in repos):
        repos.remove(repo)
    if module_name in bpy.context.preferences.addons:
        addon_utils.disable(module_name, default_set=True)
