"""Interoperability: ARKit-52 blendshape coefficients (:mod:`jaxface.interop.arkit`) and glTF
2.0 export of a subject's rig and fits (:mod:`jaxface.interop.gltf`)."""
