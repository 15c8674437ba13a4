"""The files stages exchange: the only contract between stages.

A stage writes its outputs through the writers here and reads its upstream
stages' outputs through the readers here, by the output names those stages
declare (``Stage.outputs``); it never imports another stage. Renaming a file
inside one of these formats changes this package, and every reader with it.

==================  ==============  =============================================
module              written by      content
==================  ==============  =============================================
calibration         calibrate       calibration.json: intrinsics per camera setting
pinhole             undistort       pinhole.json: pinhole intrinsics, photo files
masks               masks           masks.json: one mask PNG per photo
cameras             sfm, synth      cameras.json: intrinsics and pose per photo
scene_folder        scene, fit_*    a self-contained Mitsuba scene folder, and the
                                    fit results beside it (params.json, log,
                                    heldout/)
==================  ==============  =============================================
"""
