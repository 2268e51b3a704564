"""Layer ``reference``: independent judges that nobody here wrote. Mitsuba 3 (a physically based
research renderer, the ``reference`` extra) renders the same cameras as the ray cache; later
issues add ground-truth targets and Blender's view of the assets. Optional: imported lazily, with
a message that says what to install."""
