// The report's and the tests' glTF viewer: three.js with its glTF loader, orbit
// controls and a neutral room environment, as one global (THREE_VIEWER).
import * as THREE from 'three';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';
import { RoomEnvironment } from 'three/examples/jsm/environments/RoomEnvironment.js';
window.THREE_VIEWER = { THREE, GLTFLoader, OrbitControls, RoomEnvironment };
