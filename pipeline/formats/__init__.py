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
sfm_report          sfm             sfm.json: how the photos were posed (SfmReport)
scene_folder        scene, fit_*    a self-contained Mitsuba scene folder, and the
                                    fit results beside it (log, heldout/)
scene_description   scene           scene.json: the scene folder's description for
                                    the fits (SceneDescription)
fit_results         fit_*           params.json: the fitted values and what the
                                    next fit takes over (MaterialFit, TexturedFit,
                                    GeometryFit)
records             -               the typed JSON records' shared base
==================  ==============  =============================================
"""
