"""The one place where configs become objects: ``checks`` refuses bad values, ``components`` finds the
classes the yaml files name, ``build`` assembles a run's parts and ``restore`` a checkpoint's model.
Everything below this package takes typed values, not a ``DictConfig``."""
